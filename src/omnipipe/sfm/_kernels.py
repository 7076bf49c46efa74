"""Compiled kernels of the camera motion (numba).

:func:`schur_blocks`: the reduced camera system's point terms, point by point
(:mod:`omnipipe.sfm.schur`).

:func:`candidate_maps`: Eq. (17)'s candidate pixels, a template's samples projected in
one block per candidate length (:mod:`omnipipe.sfm.laser_scale`).

:func:`two_smallest_columns`: the backward nearest-descriptor search read off the
forward search's product (:func:`omnipipe.sfm.features.match_features`).
"""

from __future__ import annotations

import numba
import numpy as np

from omnipipe.camera._kernels import project_block


@numba.njit(cache=True, nogil=True)
def schur_blocks(indptr, indices, data, vinv, gp, n_pose):  # pragma: no cover - compiled
    """``W V^-1 W^T`` (n_pose, n_pose) and ``W V^-1 gp`` (n_pose,), summed point by point.

    ``W`` (n_pose, 3 P) is given column-wise (CSC: ``indptr`` (3 P + 1,), ``indices``,
    ``data``), point p's columns 3p..3p+2; ``vinv`` (P, 3, 3) the inverses of the
    points' diagonal blocks; ``gp`` (3 P,) the points' gradient. Each point adds
    ``W_p V_p^-1 W_p^T`` on the rows of the poses that see it only (a few), which a
    general sparse product of ``W V^-1`` with ``W^T`` spends most of its time finding.
    """
    n_pts = vinv.shape[0]
    S = np.zeros((n_pose, n_pose))
    b = np.zeros(n_pose)
    slot = np.full(n_pose, -1, np.int64)
    rows = np.empty(n_pose, np.int64)
    for p in range(n_pts):
        nr = 0
        for c in range(3 * p, 3 * p + 3):
            for jj in range(indptr[c], indptr[c + 1]):
                r = indices[jj]
                if slot[r] < 0:
                    slot[r] = nr
                    rows[nr] = r
                    nr += 1
        if nr == 0:
            continue
        Wp = np.zeros((nr, 3))
        for c in range(3):
            for jj in range(indptr[3 * p + c], indptr[3 * p + c + 1]):
                Wp[slot[indices[jj]], c] += data[jj]
        A = Wp @ vinv[p]  # (nr, 3)
        for a in range(nr):
            ra = rows[a]
            b[ra] += A[a, 0] * gp[3 * p] + A[a, 1] * gp[3 * p + 1] + A[a, 2] * gp[3 * p + 2]
            for e in range(nr):
                S[ra, rows[e]] += A[a, 0] * Wp[e, 0] + A[a, 1] * Wp[e, 1] + A[a, 2] * Wp[e, 2]
        for a in range(nr):
            slot[rows[a]] = -1
    return S, b


@numba.njit(cache=True, error_model="numpy")
def candidate_maps(
    plane, scales, direction, kind, params, with_sheet, normal, offset, step, half, weight,
    outside, map_x, map_y, w,
):  # pragma: no cover - compiled
    """The pixels (float32 remap maps, ``outside`` where not valid) and, with the sheet,
    the weights ``w`` (N, S, K) of Eq. (17)'s candidates: template sample k of point n
    (``plane`` (N, K, 3), rig b, mm) moved by ``scales[n, s]`` (N, S) along ``direction``
    (3,), projected by the compiled camera (``kind``, ``params``); a weight is
    ``weight[n, k]`` where the moved sample lies farther than ``half[n]`` samples of
    ``step[n]`` mm from the laser sheet (``normal`` . x + ``offset`` = 0), else 0.

    Bit for bit :func:`omnipipe.sfm.laser_scale._candidate_maps` (the point-by-point
    reference), the K samples of a candidate projected as one block
    (:func:`~omnipipe.camera._kernels.project_block`).
    """
    n_pts, k_len = plane.shape[0], plane.shape[1]
    n_s = scales.shape[1]
    px, py, pz = np.empty(k_len), np.empty(k_len), np.empty(k_len)
    col, row = np.empty(k_len), np.empty(k_len)
    valid = np.empty(k_len, np.bool_)
    for i in range(n_pts):
        for k in range(k_len):
            px[k], py[k], pz[k] = plane[i, k, 0], plane[i, k, 1], plane[i, k, 2]
        for j in range(n_s):
            s0 = scales[i, j] * direction[0]
            s1 = scales[i, j] * direction[1]
            s2 = scales[i, j] * direction[2]
            project_block(kind, params, px, py, pz, (s0, s1, s2), k_len, col, row, valid)
            base = (i * n_s + j) * k_len
            for k in range(k_len):
                map_x[base + k] = col[k] if valid[k] else outside
                map_y[base + k] = row[k] if valid[k] else outside
            if with_sheet:
                for k in range(k_len):
                    along = (px[k] + s0) * normal[0] + (py[k] + s1) * normal[1] + (pz[k] + s2) * normal[2]
                    rows = abs(along + offset) / step[i]
                    w[i, j, k] = weight[i, k] * (1.0 if rows > half[i] else 0.0)


@numba.njit(cache=True, nogil=True)
def two_smallest_columns(qq, tt, dot, cols):  # pragma: no cover - compiled
    """Per column ``c`` of ``cols`` (C,): over the rows r of ``tt[c] + qq[r] - 2 dot[r, c]``
    (float32; ``qq`` (R,), ``tt`` (T,), ``dot`` (R, T)) the argmin, min and second min
    (clipped at 0): the two nearest rows of each column, in the order and with the
    comparisons of a row-wise scan of the transposed product (the first of equal
    minima wins), so the same result as a search of its own on ``dot[:, cols].T``.
    """
    n_rows = dot.shape[0]
    n_cols = cols.shape[0]
    best = np.zeros(n_cols, np.int64)
    b0 = np.full(n_cols, np.float32(np.inf))
    b1 = np.full(n_cols, np.float32(np.inf))
    two = np.float32(2.0)
    for r in range(n_rows):
        for i in range(n_cols):
            c = cols[i]
            d = tt[c] + qq[r] - two * dot[r, c]
            if d < b0[i]:
                b1[i] = b0[i]
                b0[i] = d
                best[i] = r
            elif d < b1[i]:
                b1[i] = d
    zero = np.float32(0.0)
    for i in range(n_cols):
        b0[i] = max(b0[i], zero)
        b1[i] = max(b1[i], zero)
    return best, b0, b1

"""Compiled kernels of the camera motion (numba).

:func:`schur_blocks`: the reduced camera system's point terms, point by point
(:mod:`omnipipe.sfm.schur`).

:func:`candidate_maps`: Eq. (17)'s candidate pixels, a template's samples projected in
one block per candidate length (:mod:`omnipipe.sfm.laser_scale`).

:func:`two_smallest_columns`: the backward nearest-descriptor search read off the
forward search's product (:func:`omnipipe.sfm.features.match_features`).

:func:`epipolar_inliers`: RANSAC's inlier test on the angular epipolar error
(:mod:`omnipipe.sfm.ransac`), one pass over the ray pairs without temporaries;
:func:`sample_hypothesis`: one RANSAC iteration's hypothesis (the eight-point algorithm
of :func:`omnipipe.sfm.geometry.eight_point` on a minimal sample) and its inliers.

:func:`robust_blocks`: the blocks of the bundle adjustment's ``H = Js^T Js`` and
``g = Js^T rs`` read straight off the Jacobian's rows, without ``Js`` or ``H``
(:mod:`omnipipe.sfm.schur`); :func:`hessian_times`: ``H dx`` from those blocks, in the
order of SciPy's CSR product.
"""

from __future__ import annotations

import math

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


@numba.njit(cache=True, nogil=True)
def epipolar_inliers(E, r1, r2, sin_threshold):  # pragma: no cover - compiled
    """(N,) bool: ray pairs ``r1``, ``r2`` (N, 3) unit rays whose angular epipolar error
    under ``E`` (3, 3) is below the angle whose sine is ``sin_threshold``: both rays
    closer than that to the other's epipolar plane, ``|r2 . E r1| < s |E r1|`` and
    ``|r1 . E^T r2| < s |E^T r2|``. :func:`omnipipe.sfm.geometry.epipolar_angle` below
    ``arcsin(sin_threshold)`` (a pair with a zero normal is not an inlier there either),
    up to rounding at the threshold itself."""
    n = r1.shape[0]
    out = np.empty(n, np.bool_)
    for i in range(n):
        x1, y1, z1 = r1[i, 0], r1[i, 1], r1[i, 2]
        x2, y2, z2 = r2[i, 0], r2[i, 1], r2[i, 2]
        a0 = E[0, 0] * x1 + E[0, 1] * y1 + E[0, 2] * z1  # E r1: the plane's normal in view 2
        a1 = E[1, 0] * x1 + E[1, 1] * y1 + E[1, 2] * z1
        a2 = E[2, 0] * x1 + E[2, 1] * y1 + E[2, 2] * z1
        b0 = E[0, 0] * x2 + E[1, 0] * y2 + E[2, 0] * z2  # E^T r2: in view 1
        b1 = E[0, 1] * x2 + E[1, 1] * y2 + E[2, 1] * z2
        b2 = E[0, 2] * x2 + E[1, 2] * y2 + E[2, 2] * z2
        near2 = abs(x2 * a0 + y2 * a1 + z2 * a2) < sin_threshold * math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        near1 = abs(x1 * b0 + y1 * b1 + z1 * b2) < sin_threshold * math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        out[i] = near2 and near1
    return out


@numba.njit(cache=True, nogil=True)
def sample_hypothesis(r1, r2, sample, sin_threshold):  # pragma: no cover - compiled
    """One RANSAC hypothesis: the essential matrix of the ray pairs ``sample`` (K,)
    (indices into ``r1``, ``r2`` (N, 3) unit rays, K >= 8) by the same operations as
    :func:`omnipipe.sfm.geometry.eight_point` (the Kronecker rows of Eq. (12), the
    last right singular vector of their reduced SVD, projected onto singular values
    (1, 1, 0)), and its (N,) inliers (:func:`epipolar_inliers` at ``sin_threshold``):
    (3, 3) E and the mask, without the per-call overhead of NumPy's small SVDs."""
    m = sample.shape[0]
    U = np.empty((m, 9))
    for k in range(m):
        i = sample[k]
        for a in range(3):
            for b in range(3):
                U[k, 3 * a + b] = r2[i, a] * r1[i, b]
    _, _, vt = np.linalg.svd(U, full_matrices=False)
    e = np.ascontiguousarray(vt[vt.shape[0] - 1]).reshape(3, 3)
    u, _, vt2 = np.linalg.svd(e)
    E = u @ np.diag(np.array([1.0, 1.0, 0.0])) @ vt2
    return E, epipolar_inliers(E, r1, r2, sin_threshold)


@numba.njit(cache=True)
def robust_blocks(indptr, indices, data, scale, rs, n_pose, n_pts):  # pragma: no cover - compiled
    """The blocks of ``H = Js^T Js`` and ``g = Js^T rs`` with ``Js = diag(scale) J``.

    ``J`` (m, n_pose + 3 n_pts) is given row-wise (CSR: ``indptr``, ``indices``,
    ``data``; each row's columns distinct). Every entry is summed over the rows in
    ascending order (as SciPy's sparse products do), so the blocks are bit for bit those
    of ``(Js.T @ Js)`` and ``Js.T @ rs``.

    Returns:
        ok: False when a row touches two points (the blocks are then not filled).
        U: (n_pose, n_pose) the poses' block (dense).
        w_indptr, w_indices, w_data: ``W`` (n_pose, 3 n_pts), the poses x points block,
            column-wise (CSC), each column's rows ascending, exact zeros left out (as
            SciPy's product leaves them out of ``H``).
        V: (n_pts, 3, 3) the points' diagonal blocks.
        g: (n,) the gradient.
    """
    ok, U, V, g, point, count = _diagonal_blocks(indptr, indices, data, scale, rs, n_pose, n_pts)
    if not ok:
        return False, U, np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), V, g
    start, order = _rows_by_point(point, count, n_pts)
    w_indptr, w_indices, w_data = _w_columns(indptr, indices, data, scale, start, order, n_pose, n_pts)
    return True, U, w_indptr, w_indices, w_data, V, g


@numba.njit(cache=True)
def _diagonal_blocks(indptr, indices, data, scale, rs, n_pose, n_pts):  # pragma: no cover - compiled
    """``U``, ``V`` and ``g`` of :func:`robust_blocks`, each row's point (-1: none) and
    the rows per point (``count[p + 1]``); ok False when a row touches two points."""
    m = indptr.shape[0] - 1
    n = n_pose + 3 * n_pts
    U = np.zeros((n_pose, n_pose))
    V = np.zeros((n_pts, 3, 3))
    g = np.zeros(n)
    point = np.full(m, -1, np.int64)
    count = np.zeros(n_pts + 1, np.int64)
    for i in range(m):
        s = scale[i]
        for ja in range(indptr[i], indptr[i + 1]):
            ca = indices[ja]
            va = s * data[ja]
            g[ca] += va * rs[i]
            if ca < n_pose:
                for jb in range(indptr[i], indptr[i + 1]):
                    cb = indices[jb]
                    if cb < n_pose:
                        U[ca, cb] += va * (s * data[jb])
            else:
                p = (ca - n_pose) // 3
                if point[i] < 0:
                    point[i] = p
                elif point[i] != p:
                    return False, U, V, g, point, count
                for jb in range(indptr[i], indptr[i + 1]):
                    cb = indices[jb]
                    if cb >= n_pose and (cb - n_pose) // 3 == p:
                        V[p, (ca - n_pose) % 3, (cb - n_pose) % 3] += va * (s * data[jb])
        if point[i] >= 0:
            count[point[i] + 1] += 1
    return True, U, V, g, point, count


@numba.njit(cache=True)
def _rows_by_point(point, count, n_pts):  # pragma: no cover - compiled
    """(start (n_pts + 1,), order): each point's rows ascending at order[start[p]:start[p + 1]]
    (a stable counting sort)."""
    start = np.cumsum(count)
    order = np.empty(start[n_pts], np.int64)
    fill = start[:n_pts].copy()
    for i in range(point.shape[0]):
        if point[i] >= 0:
            order[fill[point[i]]] = i
            fill[point[i]] += 1
    return start, order


@numba.njit(cache=True)
def _w_capacity(indptr, indices, start, order, n_pose, n_pts):  # pragma: no cover - compiled
    """An upper bound of ``W``'s entries: 3 x the poses each point's rows touch."""
    seen = np.zeros(n_pose, np.bool_)
    rows = np.empty(n_pose, np.int64)
    cap = 0
    for p in range(n_pts):
        nr = 0
        for q in range(start[p], start[p + 1]):
            i = order[q]
            for ja in range(indptr[i], indptr[i + 1]):
                ca = indices[ja]
                if ca < n_pose and not seen[ca]:
                    seen[ca] = True
                    rows[nr] = ca
                    nr += 1
        for a in range(nr):
            seen[rows[a]] = False
        cap += 3 * nr
    return cap


@numba.njit(cache=True)
def _w_columns(indptr, indices, data, scale, start, order, n_pose, n_pts):  # pragma: no cover - compiled
    """``W`` of :func:`robust_blocks` column-wise: the pose columns of each point's rows,
    ascending, exact zeros left out."""
    seen = np.zeros(n_pose, np.bool_)
    acc = np.zeros((n_pose, 3))
    rows = np.empty(n_pose, np.int64)
    w_indptr = np.zeros(3 * n_pts + 1, np.int64)
    cap = _w_capacity(indptr, indices, start, order, n_pose, n_pts)
    w_indices = np.empty(cap, np.int64)
    w_data = np.empty(cap)
    nnz = 0
    for p in range(n_pts):
        nr = 0
        for q in range(start[p], start[p + 1]):
            i = order[q]
            s = scale[i]
            for ja in range(indptr[i], indptr[i + 1]):
                ca = indices[ja]
                if ca >= n_pose:
                    continue
                if not seen[ca]:
                    seen[ca] = True
                    rows[nr] = ca
                    nr += 1
                va = s * data[ja]
                for jb in range(indptr[i], indptr[i + 1]):
                    cb = indices[jb]
                    if cb >= n_pose:
                        acc[ca, (cb - n_pose) % 3] += va * (s * data[jb])
        sel = np.sort(rows[:nr])
        for c in range(3):
            for a in range(nr):
                v = acc[sel[a], c]
                if v != 0.0:
                    w_indices[nnz] = sel[a]
                    w_data[nnz] = v
                    nnz += 1
            w_indptr[3 * p + c + 1] = nnz
        for a in range(nr):
            seen[sel[a]] = False
            acc[sel[a], 0] = 0.0
            acc[sel[a], 1] = 0.0
            acc[sel[a], 2] = 0.0
    return w_indptr, w_indices[:nnz], w_data[:nnz]


@numba.njit(cache=True)
def hessian_times(U, w_indptr, w_indices, w_data, V, dx):  # pragma: no cover - compiled
    """``H dx`` (n,) for ``H = [[U, W], [W^T, V]]`` (``W`` column-wise as
    :func:`robust_blocks` returns it, ``V`` (P, 3, 3) block-diagonal), each row summed
    over its nonzero entries in ascending column order: bit for bit SciPy's CSR
    ``H @ dx``."""
    n_pose = U.shape[0]
    n_pts = V.shape[0]
    y = np.zeros(n_pose + 3 * n_pts)
    for a in range(n_pose):
        s = 0.0
        for b in range(n_pose):
            if U[a, b] != 0.0:
                s += U[a, b] * dx[b]
        y[a] = s
    for col in range(3 * n_pts):
        p, c = col // 3, col % 3
        s = 0.0
        for jj in range(w_indptr[col], w_indptr[col + 1]):
            a = w_indices[jj]
            y[a] += w_data[jj] * dx[n_pose + col]
            s += w_data[jj] * dx[a]
        for c2 in range(3):
            if V[p, c, c2] != 0.0:
                s += V[p, c, c2] * dx[n_pose + 3 * p + c2]
        y[n_pose + col] = s
    return y


# --- wall15: the unrolled wall's sample maps (omnipipe.sfm.wall_shift) ---


@numba.njit(cache=True, nogil=True, error_model="numpy")
def wall_maps(kind, params, x, y, z, map_col, map_row, seen):  # pragma: no cover - compiled
    """The pixels of the wall samples (``x[c]``, ``y[c]``, ``z[r]``) (mm, rig frame; (C,),
    (C,), (R,)): (R, C) float32 ``map_col``, ``map_row`` (-10 where not valid, the value
    :func:`cv2.remap` reads as outside) and (R, C) ``seen`` (valid), each
    :func:`~omnipipe.camera._kernels.project_point` bit for bit, a row at a time through
    :func:`~omnipipe.camera._kernels.project_block` (:func:`omnipipe.sfm.wall_shift.unrolled_wall`)."""
    n = x.shape[0]
    zs = np.empty(n)
    col, row = np.empty(n), np.empty(n)
    ok = np.empty(n, np.bool_)
    for r in range(z.shape[0]):
        for c in range(n):
            zs[c] = z[r]
        project_block(kind, params, x, y, zs, (0.0, 0.0, 0.0), n, col, row, ok)
        for c in range(n):
            seen[r, c] = ok[c]
            map_col[r, c] = np.float32(col[c]) if ok[c] else np.float32(-10.0)
            map_row[r, c] = np.float32(row[c]) if ok[c] else np.float32(-10.0)

"""Compiled kernels of the bundle adjustment's normal equations (numba).

:func:`robust_blocks`: the blocks of ``H = Js^T Js`` and ``g = Js^T rs`` read straight
off the Jacobian's rows (:mod:`omnipipe.sfm.normal_equations`), without ``Js`` or ``H``.

:func:`hessian_times`: ``H dx`` from those blocks, in the order of SciPy's CSR product.
"""

from __future__ import annotations

import numba
import numpy as np


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
                    return False, U, np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros(0), V, g
                for jb in range(indptr[i], indptr[i + 1]):
                    cb = indices[jb]
                    if cb >= n_pose and (cb - n_pose) // 3 == p:
                        V[p, (ca - n_pose) % 3, (cb - n_pose) % 3] += va * (s * data[jb])
        if point[i] >= 0:
            count[point[i] + 1] += 1
    # The rows of each point, in ascending order (a stable counting sort).
    start = np.cumsum(count)
    order = np.empty(start[n_pts], np.int64)
    fill = start[:n_pts].copy()
    for i in range(m):
        if point[i] >= 0:
            order[fill[point[i]]] = i
            fill[point[i]] += 1
    # W's columns: the pose columns of each point's rows, ascending; zeros left out.
    seen = np.zeros(n_pose, np.bool_)
    acc = np.zeros((n_pose, 3))
    rows = np.empty(n_pose, np.int64)
    w_indptr = np.zeros(3 * n_pts + 1, np.int64)
    cap = 0
    for p in range(n_pts):  # an upper bound of W's entries
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
    return True, U, w_indptr, w_indices[:nnz], w_data[:nnz], V, g


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

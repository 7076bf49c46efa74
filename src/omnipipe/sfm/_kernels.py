"""Compiled kernels of the camera motion (numba).

:func:`schur_blocks`: the reduced camera system's point terms, point by point
(:mod:`omnipipe.sfm.schur`).
"""

from __future__ import annotations

import numba
import numpy as np


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

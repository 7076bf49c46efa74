"""Two-view geometry on unit ray vectors (paper Sec. V-B, Eq. 10-16).

Convention: ``rays1`` in rig 1, ``rays2`` in rig 2, and the relative transform
``rig2_from_rig1`` = (R, t): a point X1 in rig 1 is R X1 + t in rig 2. Then

    rays2^T E rays1 = 0,  E = [t]x R                      (Eq. (10))

The paper writes r'^T E r = 0 with E = R T, T = [t]x (Eq. (15), Eq. (16)); with r = rays1 and
r' = rays2 its (R, t) is the motion expressed in the other frame, the same
essential matrix up to that change of convention. Rays may point anywhere on the
sphere (omni-directional): cheirality asks for positive depth along both rays,
never for z > 0.
"""

from __future__ import annotations

import numpy as np

from omnipipe.errors import ShapeError
from omnipipe.geometry import make_transform


def _check_pairs(rays1: np.ndarray, rays2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r1 = np.asarray(rays1, float)
    r2 = np.asarray(rays2, float)
    if r1.ndim != 2 or r1.shape[1] != 3 or r1.shape != r2.shape:
        raise ShapeError(
            f"rays: expected two (N, 3) arrays of one N, got {r1.shape} and {r2.shape}"
        )
    return r1, r2


def eight_point(
    rays1: np.ndarray, rays2: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Essential matrix from >= 8 ray pairs (Eq. (11)-(14)), projected onto the essential manifold.

    Each pair gives u_i^T e = 0 (Eq. (11)) with u_i the Kronecker product of the rays
    (Eq. (12)) and e the stacked entries of E (Eq. (13)); e minimises ||U e||^2 (Eq. (14)):
    the right singular vector of U with the smallest singular value. Unit rays are
    already well conditioned (every entry in [-1, 1]), so no further normalisation
    is needed. The result has singular values (1, 1, 0).
    """
    r1, r2 = _check_pairs(rays1, rays2)
    if len(r1) < 8:
        raise ShapeError(f"eight_point: needs at least 8 ray pairs, got {len(r1)}")
    # Eq. (12): u_i = [x x', y x', z x', x y', y y', z y', x z', y z', z z'].
    U = (r2[:, :, None] * r1[:, None, :]).reshape(-1, 9)
    if weights is not None:
        U = U * np.asarray(weights, float)[:, None]
    _, _, vt = np.linalg.svd(U, full_matrices=False)
    E = vt[-1].reshape(3, 3)  # Eq. (13)-(14)
    u, _, vt2 = np.linalg.svd(E)
    return u @ np.diag([1.0, 1.0, 0.0]) @ vt2


def triangulate_pairs(
    rays1: np.ndarray, rays2: np.ndarray, rig2_from_rig1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation of ray pairs: the package's one triangulation of two views.

    Each pair's point is the midpoint of the shortest segment between the ray
    lam1 rays1 from rig 1's centre and the ray lam2 rays2 from rig 2's (least squares
    in (lam1, lam2)).

    Returns:
        points_in_rig1: (N, 3).
        depths: (N, 2) distances along rays1 (from rig 1) and rays2 (from rig 2), in
        units of the rays' lengths; both positive for points in front of both views;
        NaN (and the point too) where the rays are parallel (sin^2 of their angle
        <= 1e-12).
    """
    r1, r2 = _check_pairs(rays1, rays2)
    R = rig2_from_rig1[:3, :3]
    t = rig2_from_rig1[:3, 3]
    c2 = -R.T @ t  # centre of rig 2 in rig 1
    d2 = r2 @ R  # rays2 in rig 1
    # Solve lam1 r1 - lam2 d2 = c2 in the least-squares sense per pair.
    a = np.einsum("ij,ij->i", r1, r1)
    b = np.einsum("ij,ij->i", r1, d2)
    c = np.einsum("ij,ij->i", d2, d2)
    p = r1 @ c2
    q = d2 @ c2
    den = a * c - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        lam1 = (c * p - b * q) / den
        lam2 = (b * p - a * q) / den
    parallel = ~(den > 1e-12 * a * c)
    lam1[parallel] = np.nan
    lam2[parallel] = np.nan
    pts = 0.5 * (lam1[:, None] * r1 + (c2 + lam2[:, None] * d2))
    return pts, np.stack([lam1, lam2], axis=1)


def decompose_essential(
    E: np.ndarray, rays1: np.ndarray, rays2: np.ndarray
) -> tuple[np.ndarray, int]:
    """rig2_from_rig1 (unit translation) from E = [t]x R, by cheirality on the rays.

    Of the four (R, +-t) candidates (Eq. 15-16), the one that puts the most ray pairs
    at positive depth along both rays wins.

    Returns:
        rig2_from_rig1: (4, 4) with |t| = 1.
        n_front: pairs in front of both views for that candidate.
    """
    u, _, vt = np.linalg.svd(E)
    if np.linalg.det(u) < 0:
        u = -u
    if np.linalg.det(vt) < 0:
        vt = -vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    best, best_n = None, -1
    for R in (u @ W @ vt, u @ W.T @ vt):
        for t in (u[:, 2], -u[:, 2]):
            T = make_transform(R, t)
            _, depth = triangulate_pairs(rays1, rays2, T)
            n = int(np.sum((depth[:, 0] > 0) & (depth[:, 1] > 0)))
            if n > best_n:
                best, best_n = T, n
    return best, best_n  # type: ignore[return-value]


def epipolar_angle(E: np.ndarray, rays1: np.ndarray, rays2: np.ndarray) -> np.ndarray:
    """(N,) angular epipolar error (rad): the larger angle of a ray from the other's epipolar plane."""
    r1, r2 = _check_pairs(rays1, rays2)
    n2 = r1 @ E.T  # normals of the epipolar planes in view 2
    n1 = r2 @ E  # ... in view 1
    with np.errstate(invalid="ignore", divide="ignore"):
        a2 = np.abs(np.einsum("ij,ij->i", r2, n2)) / np.linalg.norm(n2, axis=1)
        a1 = np.abs(np.einsum("ij,ij->i", r1, n1)) / np.linalg.norm(n1, axis=1)
    return np.arcsin(np.clip(np.nan_to_num(np.maximum(a1, a2), nan=1.0), 0.0, 1.0))


def rotation_from_rays(rays1: np.ndarray, rays2: np.ndarray) -> np.ndarray:
    """Pure-rotation model: the R minimising sum |rays2 - R rays1|^2 (Kabsch)."""
    r1, r2 = _check_pairs(rays1, rays2)
    u, _, vt = np.linalg.svd(r2.T @ r1)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt

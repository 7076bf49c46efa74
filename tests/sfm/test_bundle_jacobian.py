"""The bundle adjustment's analytic Jacobian against finite differences."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.camera import CameraModel, OmniCamera
from omnipipe.sfm.bundle import BundleObjective, _so3_left_jacobian


def test_so3_left_jacobian_matches_finite_differences(central_differences) -> None:
    rng = np.random.default_rng(0)
    rotvecs = np.concatenate([
        rng.normal(0, 1.0, (20, 3)),
        rng.normal(0, 1e-2, (5, 3)),
        rng.normal(0, 1e-4, (5, 3)),  # series branch
        np.zeros((1, 3)),
        [[0.0, 0.0, 3.0]],
        rng.normal(0, 1e-3, (5, 3)) * [[1, 1, 1]] / np.sqrt(3) * 1.0001,  # around the branch switch
    ])
    X = rng.normal(0, 100.0, 3)
    for w, Jl in zip(rotvecs, _so3_left_jacobian(rotvecs), strict=True):
        R = Rotation.from_rotvec(w).as_matrix()
        fd = central_differences(lambda v: Rotation.from_rotvec(v).as_matrix() @ X, w, np.full(3, 1e-6))
        # d (R(w) X) / d w = -[R X]x Jl(w)
        q = R @ X
        skew = np.array([[0, -q[2], q[1]], [q[2], 0, -q[0]], [-q[1], q[0], 0]])
        assert np.abs(-skew @ Jl - fd).max() < 1e-5 * np.abs(fd).max()


class _GenericJacobianCamera(CameraModel):
    """A camera with only the interface's generic (central-difference) Jacobian."""

    def __init__(self, camera: OmniCamera) -> None:
        self._camera = camera

    def project(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._camera.project(q)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        return self._camera.unproject(pixels)


def test_bundle_jacobian_matches_finite_differences(bundle_problem, central_differences) -> None:
    for seed, fixed, wrap in [(1, 1, False), (2, 2, False), (3, 1, True)]:
        camera, problem = bundle_problem(seed, fixed)
        if wrap:
            camera = _GenericJacobianCamera(camera)
        objective = BundleObjective(camera, problem, 2.0)
        x0, residuals, jacobian = objective.x0, objective.residuals, objective.jacobian
        r = residuals(x0)
        zeroed = r == 0
        assert 0 < zeroed.sum() < len(r) // 2  # some projections are invalid
        J = jacobian(x0)
        assert J.shape == (len(r), len(x0))
        J = J.toarray()
        fd = central_differences(residuals, x0, 1e-6 * np.maximum(1.0, np.abs(x0)))
        # Rows whose validity flips within the step are not differentiable: skip them.
        h = 1e-6 * np.maximum(1.0, np.abs(x0))
        flips = np.zeros(len(r), bool)
        for i in range(len(x0)):
            e = np.zeros(len(x0))
            e[i] = h[i]
            flips |= (residuals(x0 + e) == 0) != zeroed
            flips |= (residuals(x0 - e) == 0) != zeroed
        ok = ~flips
        assert ok.sum() > 0.9 * len(r)
        # Per row, relative to its largest derivative (an anchor within one keyframe is
        # constant: only rounding noise there).
        scale = np.maximum(np.abs(fd[ok]).max(axis=1, keepdims=True), 1e-3 * np.abs(fd).max())
        assert (np.abs(J[ok] - fd[ok]) / scale).max() < 1e-5
        assert np.all(J[zeroed] == 0)
        # Nothing outside the old sparsity: residual rows touch their own pose(s) and point.
        assert np.abs(fd[ok][J[ok] == 0]).max() < 1e-6 * np.abs(fd).max()


def test_step_length_prior_jacobian_matches_finite_differences(bundle_problem, central_differences) -> None:
    """The step-length priors' rows (each touches its two poses) against central
    differences; a prior on a fixed keyframe pair's first has entries for the free one only."""
    camera, problem = bundle_problem(4, 2)
    problem.prior_a = np.array([0, 1, 2, 3, 1])
    problem.prior_b = np.array([1, 2, 3, 4, 3])
    problem.prior_mm = np.array([20.0, 25.0, 30.0, 22.0, 50.0])
    problem.prior_sigma_mm = np.array([0.3, 0.5, 0.4, 0.2, 1.0])
    objective = BundleObjective(camera, problem, 1.0, 7.0)
    x0 = objective.x0
    r = objective.residuals(x0)
    S = len(problem.prior_a)
    J = objective.jacobian(x0).toarray()[-S:]
    h = 1e-6 * np.maximum(1.0, np.abs(x0))
    fd = central_differences(lambda x: objective.residuals(x)[-S:], x0, h)
    assert np.abs(J - fd).max() < 1e-5 * np.abs(fd).max()
    assert np.abs(fd[0]).max() == 0 and np.all(J[0] == 0)  # keyframes 0, 1 fixed: constant
    # Residual: weight (|C_b - C_a| - length) / sigma.
    C = problem.world_from_rig[:, :3, 3]
    want = 7.0 * (np.linalg.norm(C[problem.prior_b] - C[problem.prior_a], axis=1) - problem.prior_mm) / problem.prior_sigma_mm
    assert np.allclose(r[-S:], want, atol=1e-6)


def test_anchor_rows_jacobian_matches_finite_differences(bundle_problem, central_differences) -> None:
    """Anchors measured along one image direction (rows (t, 0)) and in 2-D (identity),
    mixed: their rows against central differences, and the residual is the rows times
    the pixel error."""
    camera, problem = bundle_problem(5, 1)
    L = len(problem.anchor_a)
    rng = np.random.default_rng(5)
    th = rng.uniform(0, 2 * np.pi, L)
    rows = np.broadcast_to(np.eye(2), (L, 2, 2)).copy()
    rows[::2] = 0.0
    rows[::2, 0] = np.column_stack([np.cos(th), np.sin(th)])[::2]
    M = len(problem.obs_frame)
    anc = slice(2 * M, 2 * M + 2 * L)
    plain = BundleObjective(camera, problem, 1.5)
    r_plain = plain.residuals(plain.x0)[anc].reshape(L, 2)
    problem.anchor_rows = rows
    objective = BundleObjective(camera, problem, 1.5)
    x0 = objective.x0
    r = objective.residuals(x0)[anc].reshape(L, 2)
    assert np.allclose(r, np.einsum("nij,nj->ni", rows, r_plain))
    assert np.all(r[::2, 1] == 0) and np.abs(r[::2, 0]).max() > 0
    J = objective.jacobian(x0).toarray()[anc]
    h = 1e-6 * np.maximum(1.0, np.abs(x0))
    fd = central_differences(lambda x: objective.residuals(x)[anc], x0, h)
    ok = np.abs(objective.residuals(x0)[anc]) > 0  # rows of invalid projections are zero
    assert np.abs(J[ok] - fd[ok]).max() < 1e-5 * np.abs(fd).max()


def _sorted_sparsity(objective: BundleObjective) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference of :meth:`BundleObjective._sparsity`: (indices, place, indptr) from every
    entry of the Jacobian's blocks (in :meth:`jacobian`'s order) sorted by (row, column)."""
    from omnipipe.sfm.bundle import _block_entries

    pr, F, o = objective.problem, objective._F, objective
    M, L, S = len(pr.obs_frame), len(pr.anchor_a), len(pr.prior_a)
    blocks = [
        _block_entries(o._obs_free, 6 * (pr.obs_frame[o._obs_free] - F), 6),
        _block_entries(np.arange(M), o.n_pose + 3 * pr.obs_point, 3),
        _block_entries(M + o._a_free, 6 * (pr.anchor_a[o._a_free] - F), 6),
        _block_entries(M + o._b_free, 6 * (pr.anchor_b[o._b_free] - F), 6),
    ]
    for free, k in ((o._pa_free, pr.prior_a), (o._pb_free, pr.prior_b)):
        blocks.append((np.repeat(2 * M + 2 * L + free, 6), ((6 * (k[free] - F))[:, None] + np.arange(6)).ravel()))
    for j, free in enumerate(o._ring_free):
        r, c = _block_entries(free, 6 * (pr.rings.kf[free, j] - F), 6)
        blocks.append((r + 2 * M + 2 * L + S, c))
    rows = np.concatenate([r for r, _ in blocks])
    cols = np.concatenate([c for _, c in blocks])
    order = np.lexsort((cols, rows))
    place = np.empty(len(order), np.int64)
    place[order] = np.arange(len(order))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=o._n_rows))])
    return cols[order], place, indptr


def test_sparsity_is_the_sorted_entries(bundle_problem, monkeypatch) -> None:
    """The Jacobian's CSR structure, counted for the observation rows a block at a time
    (blocks of 7 observations: many, a ragged last one; observations in any order, some
    on fixed keyframes) and sorted for the anchor, prior and ring rows (a ring with a
    keyframe twice), is every entry sorted by (row, column), in int32."""
    from omnipipe.sfm import bundle
    from omnipipe.sfm.ring_axis import AxisRows

    monkeypatch.setattr(bundle, "SPARSITY_BLOCK", 7)
    for seed, fixed in [(4, 1), (5, 2), (6, 3)]:
        camera, problem = bundle_problem(seed, fixed)
        rng = np.random.default_rng(seed)
        perm = rng.permutation(len(problem.obs_frame))
        problem.obs_frame, problem.obs_point = problem.obs_frame[perm], problem.obs_point[perm]
        problem.obs_pixels = problem.obs_pixels[perm]
        problem.prior_a, problem.prior_b = np.array([0, 1, 3, 2]), np.array([1, 2, 4, 2])
        problem.prior_mm, problem.prior_sigma_mm = np.full(4, 20.0), np.full(4, 0.5)
        kf = np.array([[0, 1, 2], [1, 2, 4], [2, 2, 3]])
        problem.rings = AxisRows(kf, rng.normal(0, 1, (3, 3, 3)), np.full(3, 0.5), rng.normal(0, 1, (3, 2, 3)),
                                 np.ones(3))
        objective = BundleObjective(camera, problem, 2.0, w_prior=3.0, w_ring=1.5)
        indices, place, indptr = _sorted_sparsity(objective)
        assert objective._indices.dtype == np.int32 and objective._place.dtype == np.int32
        assert np.array_equal(objective._indices, indices)
        assert np.array_equal(objective._place, place)
        assert np.array_equal(objective._indptr, indptr) and objective._indptr.dtype == np.int32
        J = objective.jacobian(objective.x0)
        J.sum_duplicates()  # the ring with keyframe 2 twice: its entries summed
        assert J.shape == (len(objective.residuals(objective.x0)), len(objective.x0)) and J.has_sorted_indices

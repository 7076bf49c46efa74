"""Levenberg-Marquardt on the reduced camera system (sfm/schur.py)."""

from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from omnipipe.executor import InlineExecutor
from omnipipe.sfm.bundle import BundleObjective
from omnipipe.sfm.schur import _damped_step, soft_l1_cost, solve, warm_in_worker, warm_kernels


def test_damped_step_solves_the_full_damped_system() -> None:
    rng = np.random.default_rng(4)
    n_pose, n_pts = 12, 9
    n = n_pose + 3 * n_pts
    # A bundle-shaped Jacobian: rows touch a few pose columns and one point's three.
    rows = []
    for p in range(n_pts):
        for _ in range(3):
            row = np.zeros(n)
            k = rng.integers(0, n_pose // 6)
            row[6 * k : 6 * k + 6] = rng.normal(size=6)
            row[n_pose + 3 * p : n_pose + 3 * p + 3] = rng.normal(size=3)
            rows.append(row)
    J = np.array(rows)
    H = J.T @ J
    g = rng.normal(size=n)
    for lam in (1e-6, 1e-2, 10.0):
        want = np.linalg.solve(H + lam * np.diag(np.diag(H)), -g)
        got = _damped_step(sp.csr_matrix(H), g, n_pose, lam)
        assert np.allclose(got, want, rtol=1e-8, atol=1e-10), lam


def test_solve_reaches_scipys_minimum_of_the_same_cost(bundle_problem) -> None:
    """Same robust cost as least_squares(loss='soft_l1'): as low a minimum (these toy
    problems have nearby local minima: within 0.1 %) and the same poses to a fraction of
    the noise (the speed is measured on real problems: docs/pipeline.md)."""
    for seed, fixed in [(1, 1), (2, 2)]:
        camera, problem = bundle_problem(seed, fixed)
        objective = BundleObjective(camera, problem, 1.0)
        x0, residuals, jacobian = objective.x0, objective.residuals, objective.jacobian
        n_pose = 6 * (len(problem.world_from_rig) - fixed)
        ref = least_squares(
            residuals, x0, jac=jacobian, loss="soft_l1", f_scale=1.0, x_scale="jac",
            method="trf", tr_solver="lsmr", max_nfev=2000, ftol=1e-12, xtol=1e-12,
        )
        got = solve(residuals, jacobian, x0, n_pose, f_scale=1.0, max_nfev=200)
        assert got.converged
        assert got.cost <= ref.cost * (1 + 1e-3)
        assert abs(soft_l1_cost(got.fun, 1.0) - got.cost) < 1e-9 * got.cost
        assert abs(soft_l1_cost(ref.fun, 1.0) - ref.cost) < 1e-9 * ref.cost  # the same cost
        # Poses (rotation vectors in rad, translations in mm) as SciPy's, well within
        # what 0.5 px of pixel noise allows.
        assert np.abs(got.x[:n_pose] - ref.x[:n_pose]).max() < 0.05


def test_solve_stops_at_the_cap_and_keeps_the_best(bundle_problem) -> None:
    camera, problem = bundle_problem(3, 1)
    objective = BundleObjective(camera, problem, 1.0)
    x0, residuals, jacobian = objective.x0, objective.residuals, objective.jacobian
    n_pose = 6 * (len(problem.world_from_rig) - 1)
    start = soft_l1_cost(residuals(x0), 1.0)
    capped = solve(residuals, jacobian, x0, n_pose, max_nfev=2)
    assert capped.nfev == 2 and not capped.converged
    assert capped.cost <= start
    assert np.array_equal(capped.fun, residuals(capped.x))


def test_schur_blocks_are_the_dense_products() -> None:
    """The compiled point-by-point ``W V^-1 W^T`` and ``W V^-1 gp`` against NumPy's dense
    products, with a duplicate entry (summed, as SciPy does), a point no pose sees and a
    point seen by every pose."""
    from omnipipe.sfm._kernels import schur_blocks

    rng = np.random.default_rng(11)
    n_pose, n_pts = 18, 7
    W = np.zeros((n_pose, 3 * n_pts))
    for p in range(n_pts):
        for k in rng.choice(n_pose // 6, size=rng.integers(1, 3), replace=False):
            W[6 * k : 6 * k + 6, 3 * p : 3 * p + 3] = rng.normal(size=(6, 3))
    W[:, 3:6] = 0.0  # point 1: seen by no pose
    W[:, 6:9] = rng.normal(size=(n_pose, 3))  # point 2: every pose
    A = rng.normal(size=(n_pts, 3, 3))
    vinv = np.linalg.inv(A @ np.transpose(A, (0, 2, 1)) + 3 * np.eye(3))
    gp = rng.normal(size=3 * n_pts)
    Wc = sp.csc_matrix(W)
    # The same matrix with entry (row 0, column 6) stored twice, in halves.
    at = int(Wc.indptr[6])
    assert Wc.indices[at] == 0
    data = np.insert(Wc.data, at, Wc.data[at] / 2)
    data[at + 1] = Wc.data[at] / 2
    indptr = Wc.indptr.copy()
    indptr[7:] += 1
    Wd = sp.csc_matrix((data, np.insert(Wc.indices, at, 0), indptr), shape=W.shape)
    assert Wd.nnz == Wc.nnz + 1
    Vinv = np.zeros((3 * n_pts, 3 * n_pts))
    for p in range(n_pts):
        Vinv[3 * p : 3 * p + 3, 3 * p : 3 * p + 3] = vinv[p]
    for m in (Wc, Wd):
        S, b = schur_blocks(m.indptr.astype(np.int64), m.indices.astype(np.int64), m.data, vinv, gp, n_pose)
        assert np.allclose(S, W @ Vinv @ W.T, rtol=1e-12, atol=1e-12)
        assert np.allclose(b, W @ Vinv @ gp, rtol=1e-12, atol=1e-12)


def _bundle_jacobian(rng: np.random.Generator, n_pose: int, n_pts: int) -> sp.csr_matrix:
    """A bundle-shaped Jacobian: observation row pairs touching one pose's six columns and
    one point's three, anchor rows touching two poses, a masked (all-zero) observation."""
    n = n_pose + 3 * n_pts
    rows = []
    for p in range(n_pts):
        for k in rng.choice(n_pose // 6, size=rng.integers(1, n_pose // 6 + 1), replace=False):
            for _ in range(2):
                row = np.zeros(n)
                row[6 * k : 6 * k + 6] = rng.normal(size=6)
                row[n_pose + 3 * p : n_pose + 3 * p + 3] = rng.normal(size=3)
                rows.append(row)
    for _ in range(5):
        row = np.zeros(n)
        a, b = rng.choice(n_pose // 6, size=2, replace=False)
        row[6 * a : 6 * a + 6], row[6 * b : 6 * b + 6] = rng.normal(size=6), rng.normal(size=6)
        rows.append(row)
    J = sp.csr_matrix(np.array(rows))
    J.data[J.indptr[2] : J.indptr[3]] = 0.0  # an invalid projection: explicit zeros
    return J


def test_reduced_system_from_the_jacobian_is_the_normal_matrix_split() -> None:
    """The blocks read off J's rows (no Js, no H) bit for bit those of SciPy's
    ``Js.T @ Js`` split, H dx bit for bit ``H @ dx``, and the steps the same; a row that
    touches two points goes through H."""
    from omnipipe.sfm.schur import _Reduced, _robust_normal_equations, _robust_reduced

    rng = np.random.default_rng(5)
    n_pose, n_pts = 24, 30
    J = _bundle_jacobian(rng, n_pose, n_pts)
    r = rng.normal(scale=2.0, size=J.shape[0])
    want = _Reduced.from_normal_matrix(*_robust_normal_equations(J, r, 1.5), n_pose)
    got = _robust_reduced(J, r, 1.5, n_pose)
    for name in ("U", "V", "diag", "g"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    for part in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(got.Wc, part), getattr(want.Wc, part)), part
    H, _ = _robust_normal_equations(J, r, 1.5)
    dx = rng.normal(size=J.shape[1])
    assert np.array_equal(got.times(dx), H @ dx)
    assert np.array_equal(got.step(1e-3), want.step(1e-3))
    # A row touching two points: through H (the same blocks as H's split).
    row = np.zeros(J.shape[1])
    row[n_pose : n_pose + 6] = 1.0
    J2 = sp.csr_matrix(sp.vstack([J, sp.csr_matrix(row)]))
    r2 = np.r_[r, 0.5]
    mixed = _robust_reduced(J2, r2, 1.5, n_pose)
    ref = _Reduced.from_normal_matrix(*_robust_normal_equations(J2, r2, 1.5), n_pose)
    H2, _ = _robust_normal_equations(J2, r2, 1.5)
    assert np.array_equal(mixed.V, ref.V) and np.array_equal(mixed.times(dx), H2 @ dx)


class _RecordingPool(ProcessPoolExecutor):
    """A local pool that runs each submitted task here (no process started) and notes it."""

    def __init__(self) -> None:
        super().__init__(max_workers=1)
        self.tasks: list[str] = []

    def submit(self, fn, /, *args, **kwargs):  # type: ignore[override]
        self.tasks.append(fn.__name__)
        done: Future = Future()
        done.set_result(fn(*args, **kwargs))
        return done


def test_the_kernels_are_warmed_by_a_local_pools_worker_only() -> None:
    """A local pool is given the warm-up (its workers share this machine's numba cache);
    inline and other executors are not (this process compiles as it did); the warm-up
    solves its two-point problem with the bundle adjustment's argument types."""
    pool = _RecordingPool()
    warm_in_worker(pool)
    assert pool.tasks == ["warm_kernels"]
    pool.shutdown()
    inline = InlineExecutor()
    warm_in_worker(inline)  # nothing submitted: would run here
    assert warm_kernels() >= 2
    from omnipipe.sfm import _kernels

    # The bundle's Jacobian has int32 indices (BundleObjective): the signature it loads.
    assert any(str(sig[0].dtype) == "int32" for sig in _kernels.robust_blocks.signatures)
    assert _kernels.schur_blocks.signatures and _kernels.hessian_times.signatures

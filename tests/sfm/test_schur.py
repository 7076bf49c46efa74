"""Levenberg-Marquardt on the reduced camera system (sfm/schur.py)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from omnipipe.sfm.bundle import BundleObjective
from omnipipe.sfm.schur import _damped_step, soft_l1_cost, solve


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

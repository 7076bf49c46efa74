"""Robust Levenberg-Marquardt for bundle adjustment, solved on the reduced camera system.

A bundle's normal equations couple few pose unknowns with many point unknowns, and
each point only with the poses that see it: the Hessian is ``[[U, W], [W^T, V]]``
with ``V`` block-diagonal (one 3 x 3 block per point). Eliminating the points (the
Schur complement ``S = U - W V^-1 W^T``, Triggs et al. 2000, Sec. 6.1) leaves a dense
system of 6 x (free keyframes) unknowns, solved exactly by Cholesky; the points follow
by back-substitution. SciPy's ``least_squares`` (trust-region reflective with LSMR)
solves each step iteratively instead, which on a 64-keyframe window of 4000 tracks took
hundreds of sparse products per step and still stopped at its evaluation cap.

The robust loss is SciPy's ``soft_l1`` on each scalar residual, rho(z) = 2 (sqrt(1 + z)
- 1) with z = (r / f)^2, cost 0.5 f^2 sum rho, and the same second-order residual and
Jacobian scaling (Triggs' correction) that ``least_squares`` applies, so both minimise
the same cost. Damping: Marquardt's, lambda x diag of the normal matrix, updated by the
ratio of the actual to the predicted reduction (Nielsen 1999).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from omnipipe.errors import ShapeError
from omnipipe.executor import shares_files
from omnipipe.sfm._kernels import hessian_times, robust_blocks, schur_blocks


@dataclass(frozen=True)
class LmResult:
    """Outcome of :func:`solve`.

    Attributes:
        x: (n,) the parameters at the lowest cost reached.
        fun: (m,) the residuals there.
        cost: the robust cost there (0.5 f^2 sum rho).
        nfev: residual evaluations.
        converged: a tolerance was met (else the evaluation cap stopped it).
    """

    x: np.ndarray
    fun: np.ndarray
    cost: float
    nfev: int
    converged: bool


def soft_l1_cost(r: np.ndarray, f_scale: float) -> float:
    """0.5 f^2 sum 2 (sqrt(1 + (r / f)^2) - 1): SciPy's soft_l1 cost of residuals ``r``."""
    z = (r / f_scale) ** 2
    return float(0.5 * f_scale**2 * np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))


def solve(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], sp.csr_matrix],
    x0: np.ndarray,
    n_pose: int,
    *,
    f_scale: float = 1.0,
    max_nfev: int = 50,
    ftol: float = 1e-8,
    xtol: float = 1e-8,
    gtol: float = 1e-8,
    lam0: float = 1e-4,
) -> LmResult:
    """Minimise the soft-L1 cost of ``fun`` from ``x0``.

    Args:
        fun: x -> (m,) residuals.
        jac: x -> (m, n) sparse Jacobian of ``fun``.
        x0: (n,) start: ``n_pose`` pose parameters first, then 3 per point.
        n_pose: pose parameters (a multiple of 6 is not required; any dense block).
        f_scale: soft-L1 scale (residual units).
        max_nfev: cap on residual evaluations.
        ftol, xtol, gtol: stop when the cost falls by less than ``ftol`` x cost in an
            accepted step the model predicted well, the step is shorter than ``xtol`` x
            (|x| + xtol), or the gradient's largest entry is below ``gtol``.
        lam0: initial damping (relative to the normal matrix's diagonal).

    Raises:
        ShapeError: the point parameters are not triples.
    """
    x = np.asarray(x0, float).copy()
    n = len(x)
    if (n - n_pose) % 3:
        raise ShapeError(f"solve: {n - n_pose} point parameters is not a multiple of 3")
    r = fun(x)
    state = _LmState(x, r, soft_l1_cost(r, f_scale), nfev=1, lam=lam0)
    converged = False
    while state.nfev < max_nfev:
        reduced = _robust_reduced(jac(state.x).tocsr(), state.r, f_scale, n_pose)
        if np.max(np.abs(reduced.g), initial=0.0) < gtol:
            converged = True
            break
        step_taken, converged = _damped_search(fun, reduced, state, f_scale, max_nfev, ftol, xtol)
        if converged or not step_taken:  # done, or the cap was reached mid-search
            break
    return LmResult(state.x, state.r, state.cost, state.nfev, converged)


def warm_kernels() -> int:
    """Compile :func:`solve`'s numba kernels (or load them from numba's cache) by solving a
    two-point problem with the argument types of a bundle adjustment's (CSR Jacobian with
    int32 indices); the evaluations it took. Executor task of :func:`warm_in_worker`."""
    n_pose, n_pts = 6, 2
    cols = np.concatenate([np.tile(np.arange(6), (8, 1)), n_pose + 3 * (np.arange(8) // 4)[:, None] + np.arange(3)], 1)
    data = np.cos(np.arange(cols.size, dtype=float)) + 2.0
    J = sp.csr_matrix((data, cols.reshape(-1).astype(np.int32), np.arange(0, cols.size + 1, 9, dtype=np.int32)),
                      shape=(8, n_pose + 3 * n_pts))
    b = np.sin(np.arange(8, dtype=float))
    return solve(lambda x: J @ x - b, lambda x: J, np.zeros(J.shape[1]), n_pose, max_nfev=3).nfev


def warm_in_worker(executor: Executor) -> None:
    """Have a worker of a local pool (``executor``) compile :func:`solve`'s kernels first
    (:func:`warm_kernels`), so that this process loads them from numba's cache, which the
    worker filled, instead of compiling them here: a compile leaves the compiler's
    memory in the process (~90 MB at a long run's first window, at the camera motion's
    high-water mark; benchmarks/RESULTS.md), a load ~15 MB. Only runs long enough for
    windowed adjustments use these kernels, so a cold cache (after an install or an edit
    of :mod:`omnipipe.sfm._kernels`) made a long run's peak higher than a short one's.
    Nothing on other executors (inline: this process compiles; a cluster's workers may
    not share this machine's cache). Results are unchanged (the same compiled code)."""
    if shares_files(executor):
        executor.submit(warm_kernels).result()


@dataclass
class _LmState:
    """Levenberg-Marquardt's iterate: parameters, residuals, cost, evaluations, damping."""

    x: np.ndarray
    r: np.ndarray
    cost: float
    nfev: int
    lam: float
    nu: float = 2.0


def _robust_normal_equations(
    J: sp.csr_matrix, r: np.ndarray, f_scale: float
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Gauss-Newton matrix H = Js^T Js and gradient g = Js^T rs of the soft-L1 cost, with
    SciPy's second-order residual and Jacobian scaling (Js = diag(s) J, s = (1 + z)^-3/4)."""
    z = (r / f_scale) ** 2
    rho1 = 1.0 / np.sqrt(1.0 + z)
    rho2 = -0.5 / (1.0 + z) ** 1.5
    scale = np.sqrt(np.maximum(rho1 + 2.0 * rho2 * z, np.finfo(float).eps))  # (1 + z)^-3/4
    Js = sp.diags(scale) @ J
    rs = r * rho1 / scale
    g = Js.T @ rs
    return (Js.T @ Js).tocsr(), g


def _robust_reduced(J: sp.csr_matrix, r: np.ndarray, f_scale: float, n_pose: int) -> _Reduced:
    """:func:`_robust_normal_equations` split for the Schur complement, its blocks read
    straight off ``J``'s rows (:func:`omnipipe.sfm._normal_kernels.robust_blocks`: no
    copy of ``J``, no ``H``; bit for bit the same blocks); through ``H`` when a row of
    ``J`` touches two points or repeats a column."""
    z = (r / f_scale) ** 2
    rho1 = 1.0 / np.sqrt(1.0 + z)
    rho2 = -0.5 / (1.0 + z) ** 1.5
    scale = np.sqrt(np.maximum(rho1 + 2.0 * rho2 * z, np.finfo(float).eps))  # (1 + z)^-3/4
    rs = r * rho1 / scale
    n_pts = (J.shape[1] - n_pose) // 3
    ok = J.has_canonical_format
    if ok:
        ok, U, w_indptr, w_indices, w_data, V, g = robust_blocks(
            J.indptr, J.indices, J.data, scale, rs, n_pose, n_pts,
        )
    if not ok:
        H, g = _robust_normal_equations(J, r, f_scale)
        return _Reduced.from_normal_matrix(H, g, n_pose)
    U += 0.0  # -0.0 -> 0.0, as H (which leaves zero sums out) holds them
    V += 0.0
    diag = np.concatenate([np.diagonal(U), V[:, np.arange(3), np.arange(3)].reshape(-1)])
    W = sp.csc_matrix((w_data, w_indices, w_indptr), shape=(n_pose, 3 * n_pts))
    return _Reduced(U, W, V, diag, g, n_pose)


def _damped_search(
    fun: Callable[[np.ndarray], np.ndarray],
    reduced: _Reduced,
    state: _LmState,
    f_scale: float,
    max_nfev: int,
    ftol: float,
    xtol: float,
) -> tuple[bool, bool]:
    """Raise the damping until a step lowers the cost; take it (updating ``state``).

    Returns:
        (step taken, converged): converged on a small gain the model predicted well, a
        step too short to matter (SciPy's ftol, xtol) or no lowering step at any damping;
        neither when the evaluation cap stopped the search.
    """
    g = reduced.g
    while state.nfev < max_nfev:
        dx = reduced.step(state.lam)
        predicted = -(g @ dx + 0.5 * dx @ reduced.times(dx))  # the model's reduction
        x_new = state.x + dx
        r_new = fun(x_new)
        state.nfev += 1
        cost_new = soft_l1_cost(r_new, f_scale) if np.all(np.isfinite(r_new)) else np.inf
        ratio = (state.cost - cost_new) / predicted if predicted > 0 else -1.0
        if cost_new < state.cost:
            small_gain = state.cost - cost_new < ftol * state.cost and ratio > 0.25
            small_step = np.linalg.norm(dx) < xtol * (np.linalg.norm(state.x) + xtol)
            state.x, state.r, state.cost = x_new, r_new, cost_new
            # Nielsen's update: less damping the better the model predicted.
            state.lam *= max(1.0 / 3.0, 1.0 - (2.0 * min(ratio, 1.0) - 1.0) ** 3)
            state.lam = max(state.lam, 1e-12)
            state.nu = 2.0
            return True, bool(small_gain or small_step)
        state.lam *= state.nu
        state.nu *= 2.0
        if state.lam > 1e12:  # no step lowers the cost: a minimum to working precision
            return False, True
    return False, False


def _damped_step(H: sp.csr_matrix, g: np.ndarray, n_pose: int, lam: float) -> np.ndarray:
    """The Levenberg-Marquardt step (H + lam diag(H)) dx = -g, with the points eliminated."""
    return _Reduced.from_normal_matrix(H, g, n_pose).step(lam)


class _Reduced:
    """One normal matrix ``H = [[U, W], [W^T, V]]`` and gradient ``g``, split for the
    Schur complement once: the damping changes between the steps tried on them, the
    blocks do not. ``U`` (n_pose, n_pose) dense, ``W`` (n_pose, 3 P) column-wise with
    each column's rows ascending, ``V`` (P, 3, 3) the points' diagonal blocks, ``diag``
    H's diagonal."""

    def __init__(
        self, U: np.ndarray, W: sp.csc_matrix, V: np.ndarray, diag: np.ndarray, g: np.ndarray, n_pose: int
    ) -> None:
        self.n_pose = n_pose
        self.n_pts = len(V)
        self.diag = diag
        self.U = U
        self.Wc = W
        self.V = V
        self.g = g
        self.gc, self.gp = g[:n_pose], g[n_pose:]
        self.H: sp.csr_matrix | None = None

    @classmethod
    def from_normal_matrix(cls, H: sp.csr_matrix, g: np.ndarray, n_pose: int) -> _Reduced:
        """The blocks of a normal matrix ``H`` (sparse) and its gradient ``g``."""
        n_pts = (H.shape[0] - n_pose) // 3
        Wc = H[:n_pose, n_pose:].tocsc()
        Wc.sort_indices()
        # The points' 3 x 3 diagonal blocks of H (undamped).
        Vcoo = H[n_pose:, n_pose:].tocoo()
        same = (Vcoo.row // 3) == (Vcoo.col // 3)
        V = np.zeros((n_pts, 3, 3))
        np.add.at(V, (Vcoo.row[same] // 3, Vcoo.row[same] % 3, Vcoo.col[same] % 3), Vcoo.data[same])
        reduced = cls(H[:n_pose, :n_pose].toarray(), Wc, V, H.diagonal(), g, n_pose)
        reduced.H = H  # H dx with whatever H holds beyond the blocks (a row of two points)
        return reduced

    def times(self, dx: np.ndarray) -> np.ndarray:
        """``H dx`` (n,) (:func:`omnipipe.sfm._normal_kernels.hessian_times`: SciPy's
        CSR product's order, bit for bit; ``H`` itself where it was given)."""
        if self.H is not None:
            return self.H @ dx
        W = self.Wc
        return hessian_times(
            self.U, W.indptr.astype(np.int64, copy=False), W.indices.astype(np.int64, copy=False),
            W.data, self.V, dx,
        )

    def step(self, lam: float) -> np.ndarray:
        """The step ``dx`` (n,) at damping ``lam``."""
        n_pose, n_pts = self.n_pose, self.n_pts
        # Unknowns no residual touches keep a unit diagonal (they do not move).
        damp = lam * np.where(self.diag > 0, self.diag, 1.0)
        U = self.U + np.diag(damp[:n_pose])
        V = self.V.copy()
        V[:, np.arange(3), np.arange(3)] += damp[n_pose:].reshape(n_pts, 3)
        V[:, np.arange(3), np.arange(3)] += np.where(self.diag[n_pose:] > 0, 0.0, 1.0).reshape(n_pts, 3)
        Vinv = np.linalg.inv(V)
        Wc = self.Wc
        WVW, WVg = schur_blocks(
            Wc.indptr.astype(np.int64, copy=False), Wc.indices.astype(np.int64, copy=False), Wc.data,
            Vinv, self.gp, n_pose,
        )
        S = U - WVW
        rhs = -self.gc + WVg
        try:
            dc = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs) if n_pose else np.zeros(0)
        except np.linalg.LinAlgError:
            dc = scipy.linalg.lstsq(S, rhs)[0]
        dp = -(Vinv @ (self.gp + Wc.T @ dc).reshape(n_pts, 3, 1)).reshape(-1) if n_pts else np.zeros(0)
        return np.concatenate([dc, dp])

"""Bundle adjustment [24] over the keyframes, metric through the laser.

Unknowns: every keyframe's ``rig_from_world`` (rotation vector, translation; the
first keyframe is fixed: it defines the world) and every feature track's point in
the world. Residuals, in image pixels through the hyperboloid camera (Eq. 1-3):

* feature observations: ``project(rig_k_from_world @ point_in_world) - pixel``;
* laser anchors (Sec. V-D in bundle form): a laser point measured in keyframe a is
  metric in a's rig frame (Eq. 5); its template match in keyframe b is an
  observation of that fixed point, ``project(rig_b_from_world @ world_from_rig_a @
  laser_point_in_a) - pixel_b``. These tie the translation lengths to millimetres, so
  the scale cannot drift along the run. The match was searched along an epipolar
  curve: only the residual's component along it counts (``anchor_rows``).
* step-length priors (optional): a keyframe step a -> b whose length an independent
  source measured (the wall's own shift, :mod:`omnipipe.sfm.step_priors`),
  ``weight (|C_b - C_a| - length) / sigma`` with C_k the rig's centre in the world.
* ring rows (optional): the laser ring's centre of keyframe k on the pipe's axis
  between its neighbours' (:mod:`omnipipe.sfm.ring_axis`), ``ring_weight P (X_k -
  (1 - f) X_a - f X_b) / sigma`` with ``X_j = world_from_rig_j @ c_j`` and P the two
  directions across the axis.

Robust soft-L1 loss with an analytic sparse Jacobian (:class:`BundleObjective`): each
residual touches one or two poses and one point, chained through q = R(omega) X + t,
the SO(3) left Jacobian of the rotation vector and the camera's
:meth:`~omnipipe.camera.CameraModel.project_jacobian`. Minimised by SciPy's
``least_squares`` (trf, LSMR) for a global adjustment, and by Levenberg-Marquardt on
the reduced camera system (:mod:`omnipipe.sfm.schur`: the points eliminated, each step
solved exactly) for the windows of a long run: there LSMR needed hundreds of sparse
products per step and stopped at its evaluation cap, where the exact steps converged
in 7-39 evaluations of 50, 5-20x faster and at a lower cost (``BundleConfig.solver``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from omnipipe.camera import CameraModel
from omnipipe.config import bounded
from omnipipe.errors import ConfigError, ReconstructionError, ShapeError
from omnipipe.geometry import invert
from omnipipe.sfm import schur
from omnipipe.sfm.features import track_labels
from omnipipe.sfm.geometry import triangulate_pairs
from omnipipe.sfm.ring_axis import AxisRows


@dataclass(frozen=True)
class BundleConfig:
    """Bundle adjustment settings.

    Attributes:
        enabled: run it (off: the pairwise chain is the result).
        loss_scale_px: soft-L1 scale: residuals beyond a few of these count linearly.
        laser_weight: weight of a laser anchor residual relative to a feature's.
        length_prior_weight: a step-length prior's residual per sigma of its length, px
            (:class:`BundleProblem`'s ``prior_*``).
        ring_weight: a ring row's residual per sigma of its centre across the axis, px
            (:class:`BundleProblem`'s ``rings``; 0: none). Large: the rows are added only
            where the adjustment without them left a centre beyond 3 sigma off the axis
            (:func:`omnipipe.sfm.adjust` ``_held_to_rings``), and the soft-L1 loss makes
            each a bounded pull; at 1-10 a step 61 matches had turned 1.2 deg too far
            stayed (robustness seed 31: ATE 1.78 -> 2.07 / 1.24 mm per 300 mm), at 30 it
            is pulled back (0.87).
        max_reprojection_px: tracks worse than this at the start are dropped.
        min_parallax_deg: tracks whose rays meet at a smaller angle are dropped
            (their depth is unconstrained).
        max_tracks: evenly chosen tracks kept (the cost grows with their number).
        max_evaluations: cap on residual evaluations.
        window_keyframes: a longer run is adjusted in consecutive windows of this many
            keyframes (:func:`keyframe_windows`): cost and memory linear in the run's
            length instead of one global adjustment (0: always global). Runs of up to
            1.25 x this are adjusted globally.
        window_overlap: keyframes each window shares with (and holds fixed from) the
            one before.
        solver: "trf" (SciPy's trust-region reflective with LSMR), "schur"
            (Levenberg-Marquardt on the reduced camera system, :mod:`omnipipe.sfm.schur`)
            or "auto", which uses both, each where the other fails: schur for the
            windows of a long run (trf stopped at the evaluation cap 5-20x slower and at
            a higher cost on every window measured), trf for a global adjustment (from a
            start far off, tests/sfm/test_bundle.py's 5 % scale error, LM settles in a
            worse local minimum: cost 0.7 % higher, poses 0.45 against 0.23 mm off; on
            paper-small, bend-small and other-rig-small the two agree within 0.001 mm).
        epipolar_anchors: a laser anchor's residual is only its component along the
            epipolar curve it was searched on (:func:`epipolar_rows`); off: both
            components, which hold each step to the motion the search assumed.
        along_min_matches: fewest RANSAC inliers of every keyframe step a laser anchor
            spans for ``epipolar_anchors`` to apply to it; across fewer (a plain wall's
            7-48 matches a step on the random-wide family) the anchor keeps both
            components: there the features do not fix the steps' directions, and the
            across component (the RANSAC motion) held keyframes the few tracks turned
            off (robustness seed 25: 6.60 mm per 300 mm, all along 7.45).
    """

    enabled: bool = True
    loss_scale_px: float = bounded(1.0, gt=0)
    laser_weight: float = bounded(1.0, ge=0)
    length_prior_weight: float = bounded(10.0, ge=0)
    ring_weight: float = bounded(30.0, ge=0)
    max_reprojection_px: float = bounded(4.0, gt=0)
    min_parallax_deg: float = bounded(1.0, ge=0, lt=180)
    max_tracks: int = bounded(4000, ge=1)
    max_evaluations: int = bounded(50, ge=1)
    window_keyframes: int = bounded(64, ge=3)
    window_overlap: int = bounded(8, ge=1)
    solver: str = "auto"
    epipolar_anchors: bool = True
    along_min_matches: int = bounded(50, ge=0)

    def __post_init__(self) -> None:
        if self.solver not in ("auto", "trf", "schur"):
            raise ConfigError("sfm.bundle.solver", f"must be auto, trf or schur, got {self.solver!r}")


@dataclass
class BundleProblem:
    """Observations of a bundle adjustment.

    Attributes:
        world_from_rig: (K, 4, 4) initial keyframe poses (keyframe 0 stays fixed).
        points_in_world: (P, 3) initial track points, mm.
        obs_frame, obs_point: (M,) keyframe and point index of each observation.
        obs_pixels: (M, 2) observed omni pixels (col, row).
        anchor_a, anchor_b: (L,) keyframes where a laser point was measured / found again.
        anchor_points_in_a: (L, 3) the laser points in rig a, mm.
        anchor_pixels_b: (L, 2) their matched pixels in keyframe b.
        feature_point: per keyframe, (N_k,) the track point of each feature (-1: none).
        fixed: the first ``fixed`` keyframes keep their poses (at least 1: the first
            defines the world; a window of a long run also holds the keyframes it shares
            with the window before, :func:`keyframe_windows`).
        prior_a, prior_b: (S,) keyframes of each step-length prior.
        prior_mm, prior_sigma_mm: (S,) each prior's length and its 1-sigma, mm.
        rings: the ring rows (:class:`omnipipe.sfm.ring_axis.AxisRows`).
        anchor_rows: (L, 2, 2) or None: each anchor's residual (px) is ``anchor_rows[i]
            @ (projection - pixel)``; None: the identity (a pixel measured in 2-D). A
            laser match searched only along an epipolar curve measured its pixel along
            that curve alone: its rows are (the curve's unit tangent, 0)
            (:func:`epipolar_rows`), so the adjustment is not held to the motion the
            search assumed.
    """

    world_from_rig: np.ndarray
    points_in_world: np.ndarray
    obs_frame: np.ndarray
    obs_point: np.ndarray
    obs_pixels: np.ndarray
    anchor_a: np.ndarray
    anchor_b: np.ndarray
    anchor_points_in_a: np.ndarray
    anchor_pixels_b: np.ndarray
    feature_point: list[np.ndarray] | None = None
    fixed: int = 1
    prior_a: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    prior_b: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    prior_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior_sigma_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rings: AxisRows = field(default_factory=AxisRows.empty)
    anchor_rows: np.ndarray | None = None


@dataclass(frozen=True)
class LengthPrior:
    """A keyframe step's length measured by a source outside the adjustment.

    Attributes:
        a, b: the step's keyframes.
        length_mm: its length, mm.
        sigma_mm: its 1-sigma, mm.
    """

    a: int
    b: int
    length_mm: float
    sigma_mm: float


def set_priors(problem: BundleProblem, priors: list[LengthPrior]) -> None:
    """Put ``priors`` (keyframes counted from the problem's first) into ``problem``."""
    problem.prior_a = np.array([p.a for p in priors], int)
    problem.prior_b = np.array([p.b for p in priors], int)
    problem.prior_mm = np.array([p.length_mm for p in priors], float)
    problem.prior_sigma_mm = np.array([p.sigma_mm for p in priors], float)


@dataclass
class BundleResult:
    """Adjusted poses and points, and the reprojection RMS before and after (px)."""

    world_from_rig: np.ndarray
    points_in_world: np.ndarray
    rms_before_px: float
    rms_after_px: float
    anchor_rms_px: float
    evaluations: int


def _poses_to_params(world_from_rig: np.ndarray) -> np.ndarray:
    rig_from_world = np.array([invert(T) for T in world_from_rig])
    rv = Rotation.from_matrix(rig_from_world[:, :3, :3]).as_rotvec()
    return np.concatenate([rv, rig_from_world[:, :3, 3]], axis=1)


def _params_to_rig_from_world(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_rotvec(p[:, :3]).as_matrix(), p[:, 3:]


def _so3_left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """(N, 3, 3) left Jacobians J of rotation vectors w: exp(w + d) = exp(J d) exp(w) to first order.

    J = I + (1 - cos th) / th^2 [w]x + (th - sin th) / th^3 [w]x^2, th = |w| (series below 1e-3).
    """
    th2 = np.einsum("ni,ni->n", rotvec, rotvec)
    th = np.sqrt(th2)
    small = th < 1e-3
    ths = np.where(small, 1.0, th)
    c1 = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / ths**2)
    c2 = np.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (ths - np.sin(ths)) / ths**3)
    W = _skew(rotvec)
    return np.eye(3) + c1[:, None, None] * W + c2[:, None, None] * (W @ W)


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices [v]x (so [v]x u = v x u)."""
    W = np.zeros((len(v), 3, 3))
    W[:, 0, 1], W[:, 0, 2] = -v[:, 2], v[:, 1]
    W[:, 1, 0], W[:, 1, 2] = v[:, 2], -v[:, 0]
    W[:, 2, 0], W[:, 2, 1] = -v[:, 1], v[:, 0]
    return W


def _masked_projection_jacobian(camera: CameraModel, q: np.ndarray) -> np.ndarray:
    """(N, 2, 3) d pixel / d q (the camera's :meth:`~CameraModel.project_jacobian`),
    zero where the residual is zeroed (invalid or non-finite)."""
    px, valid = camera.project(q)
    J = camera.project_jacobian(q)
    keep = valid & np.isfinite(px).all(axis=1) & np.isfinite(J).all(axis=(1, 2))
    J[~keep] = 0.0
    return J


def epipolar_rows(
    camera: CameraModel,
    world_from_rig: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    points_in_a: np.ndarray,
    along: np.ndarray,
) -> np.ndarray:
    """(L, 2, 2) anchor rows (:class:`BundleProblem`'s ``anchor_rows``): for the anchors
    ``along`` ((L,) bool) measured only along their epipolar curve, (t, 0) with t the
    curve's unit tangent in keyframe b's image at the point (the image direction in
    which the point of rig a moves as the step a -> b lengthens, under the poses
    ``world_from_rig`` (K, 4, 4) the search assumed); the identity for the others and
    where the tangent is undefined (no translation, no projection).

    Args:
        a, b: (L,) keyframes of each anchor.
        points_in_a: (L, 3) the anchors' points in rig a, mm.
    """
    L = len(a)
    rows = np.broadcast_to(np.eye(2), (L, 2, 2)).copy()
    if not np.any(along):
        return rows
    b_from_a = np.linalg.inv(world_from_rig[b]) @ world_from_rig[a]
    q = np.einsum("nij,nj->ni", b_from_a[:, :3, :3], points_in_a) + b_from_a[:, :3, 3]
    d = b_from_a[:, :3, 3]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    tangent = np.einsum("nij,nj->ni", camera.project_jacobian(q), d)
    norm = np.linalg.norm(tangent, axis=1)
    ok = along & np.isfinite(norm) & (norm > 1e-12) & camera.project(q)[1]
    rows[ok] = 0.0
    rows[ok, 0, :] = tangent[ok] / norm[ok, None]
    return rows


def _check_shapes(problem: BundleProblem) -> None:
    """Raises ShapeError on observation or anchor arrays of inconsistent shapes, or a bad ``fixed``."""
    K = len(problem.world_from_rig)
    M, L = len(problem.obs_frame), len(problem.anchor_a)
    if problem.obs_pixels.shape != (M, 2) or problem.obs_point.shape != (M,):
        raise ShapeError(f"bundle_adjust: observations of inconsistent shapes {problem.obs_pixels.shape}")
    if problem.anchor_points_in_a.shape != (L, 3) or problem.anchor_pixels_b.shape != (L, 2):
        raise ShapeError(f"bundle_adjust: anchors of inconsistent shapes {problem.anchor_points_in_a.shape}")
    if problem.anchor_rows is not None and problem.anchor_rows.shape != (L, 2, 2):
        raise ShapeError(f"bundle_adjust: anchor rows of shape {problem.anchor_rows.shape}, want ({L}, 2, 2)")
    if not 1 <= int(problem.fixed) <= K:
        raise ShapeError(f"bundle_adjust: fixed must be 1..{K} keyframes, got {int(problem.fixed)}")
    S = len(problem.prior_a)
    if not (len(problem.prior_b) == len(problem.prior_mm) == len(problem.prior_sigma_mm) == S):
        raise ShapeError("bundle_adjust: step-length priors of inconsistent shapes")


def _block_entries(rows: np.ndarray, col0: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) indices of a (2, width) Jacobian block per residual pair ``rows``, from column ``col0``."""
    r = np.broadcast_to((2 * rows)[:, None, None] + np.arange(2)[None, :, None], (len(rows), 2, width))
    c = np.broadcast_to(col0[:, None, None] + np.arange(width)[None, None, :], (len(rows), 2, width))
    return r.ravel(), c.ravel()


SPARSITY_BLOCK = 1 << 16
"""Observations whose Jacobian entries :meth:`BundleObjective._sparsity` places at a time."""


class BundleObjective:
    """A bundle adjustment's parameters, residuals and analytic sparse Jacobian.

    ``x`` holds the free keyframes' (rotation vector, translation) of rig_from_world
    (6 each), then the points (3 each, mm). Residuals (2M observation rows, then 2L
    anchor rows, then S step-length prior rows, px) are in the order of
    :class:`BundleProblem`'s arrays; an invalid or non-finite projection gives a zero
    residual.

    Attributes:
        x0: the start (the problem's initial poses and points).
        n_pose: pose parameters in ``x``: 6 x (K - fixed).

    Raises:
        ShapeError: inconsistent observation arrays.
    """

    def __init__(
        self, camera: CameraModel, problem: BundleProblem, w_laser: float, w_prior: float = 0.0,
        w_ring: float = 0.0,
    ) -> None:
        _check_shapes(problem)
        self.camera, self.problem, self.w_laser = camera, problem, w_laser
        self.w_prior = w_prior
        rings = problem.rings
        # Each ring row's weight on X_a, X_k, X_b, per mm: -(1 - f), 1, -f over sigma.
        self._ring_coef = (
            w_ring
            * np.column_stack([-(1.0 - rings.fraction), np.ones(len(rings)), -rings.fraction])
            / np.maximum(rings.sigma_mm, 1e-9)[:, None]
        )
        K, F = len(problem.world_from_rig), int(problem.fixed)
        pose0 = _poses_to_params(problem.world_from_rig)
        self._fixed = pose0[:F].copy()
        self._F = F
        self.n_pose = 6 * (K - F)
        self.x0 = np.concatenate([pose0[F:].ravel(), problem.points_in_world.ravel()])
        self._sparsity()

    def _sparsity(self) -> None:
        """The Jacobian's structure (row-major CSR, computed once): observation rows touch
        their pose (unless fixed) and point; anchor rows two poses (unless fixed; an anchor
        within one keyframe is constant: no entries).

        The observation rows come first and each holds its pose's 6 columns (if free) and
        then its point's 3 (point columns follow every pose column): their CSR places are
        counted, not sorted, a block of :data:`SPARSITY_BLOCK` observations at a time, in
        int32 where the entries allow. Only the few other rows (anchors, priors, rings)
        are sorted, as entries of their blocks. ``_indices``, ``_place`` and ``_indptr``
        are those of sorting every entry by (row, column) (``_place``: where each entry of
        :meth:`jacobian`'s blocks, concatenated, goes in CSR order). The freed pages are
        handed back to the system before the solve
        (:func:`omnipipe.memory.release_freed_memory`)."""
        from omnipipe.memory import release_freed_memory

        pr, F = self.problem, self._F
        M, L = len(pr.obs_frame), len(pr.anchor_a)
        self._obs_free = np.flatnonzero(pr.obs_frame >= F)
        self._a_free = np.flatnonzero((pr.anchor_a >= F) & (pr.anchor_a != pr.anchor_b))
        self._b_free = np.flatnonzero((pr.anchor_b >= F) & (pr.anchor_a != pr.anchor_b))
        S, T = len(pr.prior_a), len(pr.rings)
        self._pa_free = np.flatnonzero(pr.prior_a >= F)
        self._pb_free = np.flatnonzero(pr.prior_b >= F)
        self._ring_free = [np.flatnonzero(pr.rings.kf[:, j] >= F) for j in range(3)]
        blocks = [
            _block_entries(M + self._a_free, 6 * (pr.anchor_a[self._a_free] - F), 6),
            _block_entries(M + self._b_free, 6 * (pr.anchor_b[self._b_free] - F), 6),
        ]
        # A prior row touches its two poses (unless fixed).
        for free, k in ((self._pa_free, pr.prior_a), (self._pb_free, pr.prior_b)):
            rows = np.repeat(2 * M + 2 * L + free, 6)
            cols = (6 * (k[free] - F))[:, None] + np.arange(6)[None, :]
            blocks.append((rows, cols.ravel()))
        # A ring row pair touches its three poses (unless fixed).
        for j, free in enumerate(self._ring_free):
            r, c = _block_entries(free, 6 * (pr.rings.kf[free, j] - F), 6)
            blocks.append((r + 2 * M + 2 * L + S, c))
        rest_rows = np.concatenate([r for r, _ in blocks])
        rest_cols = np.concatenate([c for _, c in blocks])
        order = np.lexsort((rest_cols, rest_rows))
        self._n_rows = 2 * M + 2 * L + S + 2 * T
        counts = np.zeros(self._n_rows, np.int64)
        counts[: 2 * M] = np.repeat(np.where(pr.obs_frame >= F, 9, 3), 2)
        counts[2 * M :] = np.bincount(rest_rows - 2 * M, minlength=self._n_rows - 2 * M)
        n_obs = int(counts[: 2 * M].sum())
        n = n_obs + len(order)
        self._indices = np.empty(n, np.int32)
        self._place = np.empty(n, np.int32 if n < 2**31 else np.int64)
        self._observation_places()
        self._indices[n_obs:] = rest_cols[order]
        self._place[len(self._obs_free) * 12 + 6 * M + order] = n_obs + np.arange(len(order))
        self._indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self._shape = (self._n_rows, len(self.x0))
        del blocks, rest_rows, rest_cols, order, counts
        # The pages freed since (this structure's work, a previous window's adjustment)
        # back to the system: not under this window's solve.
        release_freed_memory()

    def _observation_places(self) -> None:
        """The observation entries' columns (the first of ``_indices``) and CSR places (the
        first ``12 x free observations + 6 M`` of ``_place``: the free observations' (2, 6)
        pose blocks, then every observation's (2, 3) point block), a block of
        :data:`SPARSITY_BLOCK` observations at a time."""
        pr, F, M = self.problem, self._F, len(self.problem.obs_frame)
        dtype = self._place.dtype
        free = pr.obs_frame >= F
        first_pose = np.concatenate([[0], np.cumsum(free)])  # free observations before each
        start = 0  # the CSR place of the block's first observation
        for a in range(0, M, SPARSITY_BLOCK):
            b = min(a + SPARSITY_BLOCK, M)
            f = free[a:b]
            width = np.where(f, 9, 3).astype(dtype)  # entries in each of its two rows
            at = start + 2 * (np.cumsum(width, dtype=dtype) - width)  # its first row's place
            row = np.arange(2, dtype=dtype)[None, :, None]
            pose = (at[f][:, None, None] + row * 9 + np.arange(6, dtype=dtype)[None, None, :]).ravel()
            point = (at[:, None, None] + row * width[:, None, None] + (6 * f).astype(dtype)[:, None, None]
                     + np.arange(3, dtype=dtype)[None, None, :]).ravel()
            self._place[12 * first_pose[a] : 12 * first_pose[b]] = pose
            self._place[12 * first_pose[-1] + 6 * a : 12 * first_pose[-1] + 6 * b] = point
            self._indices[pose] = np.repeat(6 * (pr.obs_frame[a:b][f] - F), 12) + np.tile(np.arange(6), 2 * int(f.sum()))
            self._indices[point] = np.repeat(self.n_pose + 3 * pr.obs_point[a:b], 6) + np.tile(np.arange(3), 2 * (b - a))
            start += 2 * int(width.sum())

    def _poses(self, x: np.ndarray) -> np.ndarray:
        """(K, 6) every keyframe's (rotation vector, translation) of rig_from_world."""
        return np.vstack([self._fixed, x[: self.n_pose].reshape(-1, 6)])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K, 3, 3) rotations and (K, 3) translations of rig_from_world, (P, 3) points in the world."""
        R, t = _params_to_rig_from_world(self._poses(x))
        return R, t, x[self.n_pose :].reshape(len(self.problem.points_in_world), 3)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(2M + 2L + S + 2T,) observation, then (weighted) anchor, prior and ring residuals, px."""
        pr, camera = self.problem, self.camera
        R, t, pts = self.unpack(x)
        k, p = pr.obs_frame, pr.obs_point
        q = np.einsum("nij,nj->ni", R[k], pts[p]) + t[k]
        px, valid = camera.project(q)
        r_obs = np.where(valid[:, None], px - pr.obs_pixels, 0.0)
        a, b = pr.anchor_a, pr.anchor_b
        # world point of the laser point: R_a^T (q_a - t_a)
        w = np.einsum("nji,nj->ni", R[a], pr.anchor_points_in_a - t[a])
        qb = np.einsum("nij,nj->ni", R[b], w) + t[b]
        pxb, vb = camera.project(qb)
        r_anc = np.where(vb[:, None], pxb - pr.anchor_pixels_b, 0.0) * self.w_laser
        if pr.anchor_rows is not None:
            r_anc = np.einsum("nij,nj->ni", pr.anchor_rows, r_anc)
        C = -np.einsum("nji,nj->ni", R, t)  # the rigs' centres in the world
        length = np.linalg.norm(C[pr.prior_b] - C[pr.prior_a], axis=1)
        r_len = self.w_prior * (length - pr.prior_mm) / pr.prior_sigma_mm
        r = np.concatenate([r_obs.ravel(), r_anc.ravel(), r_len, self._ring_residuals(R, t)])
        return np.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0)

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        """(2M + 2L, len(x)) sparse CSR d residuals / d x."""
        R, t, pts = self.unpack(x)
        Jl = _so3_left_jacobian(self._poses(x)[:, :3])
        d_pose_obs, d_point = self._observation_blocks(R, t, pts, Jl)
        d_pose_a, d_pose_b = self._anchor_blocks(R, t, Jl)
        d_prior_a, d_prior_b = self._prior_blocks(R, t, Jl)
        data = np.empty(len(self._place))
        at = 0
        blocks = (d_pose_obs, d_point, d_pose_a, d_pose_b, d_prior_a, d_prior_b, *self._ring_blocks(R, t, Jl))
        for block in blocks:
            data[self._place[at : at + block.size]] = block.ravel()  # straight into CSR order
            at += block.size
        return csr_matrix((data, self._indices, self._indptr), shape=self._shape)

    def _prior_blocks(self, R: np.ndarray, t: np.ndarray, Jl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free a, 6) and (free b, 6): d prior residual / d pose a and / d pose b.

        C = -R^T t; with R -> exp(d) R, d C = -R^T [t]x d, d = Jl d omega; d C / d t = -R^T.
        """
        pr = self.problem
        C = -np.einsum("nji,nj->ni", R, t)
        diff = C[pr.prior_b] - C[pr.prior_a]
        u = diff / np.maximum(np.linalg.norm(diff, axis=1), 1e-12)[:, None]
        u = u * (self.w_prior / pr.prior_sigma_mm)[:, None]

        def d_centre(k: np.ndarray, ui: np.ndarray) -> np.ndarray:
            uR = np.einsum("ni,nji->nj", ui, R[k])  # u^T R^T
            return -np.concatenate([np.einsum("ni,nij->nj", uR, _skew(t[k]) @ Jl[k]), uR], axis=1)

        fa, fb = self._pa_free, self._pb_free
        return -d_centre(pr.prior_a[fa], u[fa]), d_centre(pr.prior_b[fb], u[fb])

    def _ring_residuals(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(2T,) the ring rows: the centre of k off its neighbours' chord, across the axis, px."""
        rings = self.problem.rings
        if not len(rings):
            return np.zeros(0)
        k = rings.kf
        # X_j = R_j^T (c_j - t_j): the ring centre in the world.
        X = np.einsum("tjip,tjp->tji", np.transpose(R[k], (0, 1, 3, 2)), rings.centres_in_rig - t[k])
        off = np.einsum("tj,tji->ti", self._ring_coef, X)
        return np.einsum("tpi,ti->tp", rings.across, off).ravel()

    def _ring_blocks(self, R: np.ndarray, t: np.ndarray, Jl: np.ndarray) -> list[np.ndarray]:
        """Per role (a, k, b), (free rows, 2, 6) d ring residual / d pose.

        d X / d t = -R^T; d X / d omega = R^T [y]x Jl(omega), y = c - t.
        """
        rings = self.problem.rings
        out = []
        for j, free in enumerate(self._ring_free):
            k = rings.kf[free, j]
            G = self._ring_coef[free, j][:, None, None] * (rings.across[free] @ np.transpose(R[k], (0, 2, 1)))
            y = rings.centres_in_rig[free, j] - t[k]
            out.append(np.concatenate([np.cross(G, y[:, None, :]) @ Jl[k], -G], axis=2))
        return out

    def _observation_blocks(
        self, R: np.ndarray, t: np.ndarray, pts: np.ndarray, Jl: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(free obs, 2, 6) d residual / d pose and (M, 2, 3) d residual / d point of the observations."""
        k, p = self.problem.obs_frame, self.problem.obs_point
        Rk = R[k]
        Rx = np.einsum("nij,nj->ni", Rk, pts[p])
        Jq = _masked_projection_jacobian(self.camera, Rx + t[k])
        # d q / d X = R; d q / d t = I; d q / d omega = -[R X]x Jl(omega).
        d_point = Jq @ Rk
        obs_free = self._obs_free
        Jf = Jq[obs_free]
        d_pose_obs = np.concatenate([np.cross(Rx[obs_free][:, None, :], Jf) @ Jl[k[obs_free]], Jf], axis=2)
        return d_pose_obs, d_point

    def _anchor_blocks(self, R: np.ndarray, t: np.ndarray, Jl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free a, 2, 6) and (free b, 2, 6): d anchor residual / d pose a and / d pose b."""
        pr = self.problem
        a, b = pr.anchor_a, pr.anchor_b
        a_free, b_free = self._a_free, self._b_free
        y = pr.anchor_points_in_a - t[a]
        w = np.einsum("nji,nj->ni", R[a], y)  # R_a^T (q_a - t_a)
        Rw = np.einsum("nij,nj->ni", R[b], w)
        Jb = _masked_projection_jacobian(self.camera, Rw + t[b]) * self.w_laser
        if pr.anchor_rows is not None:
            Jb = pr.anchor_rows @ Jb
        # Pose b as an observation of w; pose a through w: d w / d t_a = -R_a^T,
        # d w / d omega_a = R_a^T [y]x Jl(omega_a).
        Ja, Jbb = Jb[a_free], Jb[b_free]
        d_pose_b = np.concatenate([np.cross(Rw[b_free][:, None, :], Jbb) @ Jl[b[b_free]], Jbb], axis=2)
        G = Ja @ R[b[a_free]] @ np.transpose(R[a[a_free]], (0, 2, 1))
        d_pose_a = np.concatenate([np.cross(G, y[a_free][:, None, :]) @ Jl[a[a_free]], -G], axis=2)
        return d_pose_a, d_pose_b


def bundle_adjust(camera: CameraModel, problem: BundleProblem, config: BundleConfig) -> BundleResult:
    """Refine keyframe poses and track points (see the module docstring).

    Raises:
        ShapeError: inconsistent observation arrays.
    """
    w_laser = float(config.laser_weight)
    objective = BundleObjective(
        camera, problem, w_laser, float(config.length_prior_weight), float(config.ring_weight)
    )
    x0, residuals, jacobian = objective.x0, objective.residuals, objective.jacobian
    K, M, L = len(problem.world_from_rig), len(problem.obs_frame), len(problem.anchor_a)
    r0 = residuals(x0)
    # Single-threaded BLAS: the result does not depend on the machine's core count
    # (threaded sums round differently: 2e-7 mm in the poses); LSMR's dot products are
    # short, so threads cost more than they save.
    with threadpool_limits(limits=1, user_api="blas"):
        if config.solver == "schur":
            sol = schur.solve(
                residuals, jacobian, x0, objective.n_pose,
                f_scale=config.loss_scale_px, max_nfev=config.max_evaluations,
            )
        else:
            sol = least_squares(
                residuals, x0, jac=jacobian, loss="soft_l1", f_scale=config.loss_scale_px,
                x_scale="jac", method="trf", tr_solver="lsmr", max_nfev=config.max_evaluations,
            )
    r1 = sol.fun
    R, t, pts = objective.unpack(sol.x)
    world_from_rig = np.empty((K, 4, 4))
    for k in range(K):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[k], t[k]
        world_from_rig[k] = invert(T)

    def rms(r: np.ndarray) -> float:
        return float(np.sqrt(np.mean(r**2))) if len(r) else 0.0

    return BundleResult(
        world_from_rig, pts, rms(r0[: 2 * M]), rms(r1[: 2 * M]),
        rms(r1[2 * M : 2 * M + 2 * L] / max(w_laser, 1e-9)), int(sol.nfev)
    )


def _select_tracks(
    pixels: list[np.ndarray], pair_matches: list[tuple[int, int, np.ndarray]], max_tracks: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Feature tracks from pairwise matches: per track, its keyframes and feature indices.

    A track is a connected set of matched features seen in at least two keyframes, at
    most one feature per keyframe (in keyframe order); beyond ``max_tracks`` the
    longest are kept.
    """
    offset = np.concatenate([[0], np.cumsum([len(p) for p in pixels])])
    roots = track_labels(offset, pair_matches)
    frame_of = np.repeat(np.arange(len(pixels)), np.diff(offset))
    local = np.arange(offset[-1]) - offset[frame_of]
    order = np.lexsort((frame_of, roots))
    roots_s, frames_s = roots[order], frame_of[order]
    dup = np.r_[False, (roots_s[1:] == roots_s[:-1]) & (frames_s[1:] == frames_s[:-1])]
    order = order[~dup]
    roots_s = roots[order]
    _, start, count = np.unique(roots_s, return_index=True, return_counts=True)
    tracks = [(start[i], count[i]) for i in np.flatnonzero(count >= 2)]
    if len(tracks) > max_tracks:
        # Prefer long tracks, then spread evenly.
        tracks.sort(key=lambda s: -s[1])
        tracks = tracks[:max_tracks]
    out = []
    for s, c in tracks:
        idx = order[s : s + c]
        out.append((frame_of[idx], local[idx]))
    return out


def _triangulate_tracks(
    camera: CameraModel,
    world_from_rig: np.ndarray,
    frames: np.ndarray,
    rays: np.ndarray,
    obs: np.ndarray,
    start: np.ndarray,
    config: BundleConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """World points of T tracks at once: each the midpoint of its first and last rays
    (the widest baseline), kept unless their parallax is below ``min_parallax_deg``,
    the point is behind either, or it reprojects anywhere worse than
    ``max_reprojection_px``.

    Args:
        world_from_rig: (K, 4, 4) keyframe poses.
        frames, rays, obs: (M,) keyframe, (M, 3) unit ray in its rig and (M, 2) omni
            pixel of each observation, track after track (each in keyframe order).
        start: (T,) where each track's observations start (the next one's start, or
            M, ends it).

    Returns:
        (T, 3) points (mm) and (T,) True for the tracks kept.
    """
    R = world_from_rig[:, :3, :3]
    C = world_from_rig[:, :3, 3]
    first, last = start, np.r_[start[1:], len(frames)] - 1
    k1, k2 = frames[first], frames[last]
    d1 = np.einsum("nij,nj->ni", R[k1], rays[first])
    d2 = np.einsum("nij,nj->ni", R[k2], rays[last])
    ok = ~(np.einsum("ni,ni->n", d1, d2) > np.cos(np.radians(config.min_parallax_deg)))
    X = np.full((len(start), 3), np.nan)
    pair_id = k1 * len(R) + k2
    for key in np.unique(pair_id[ok]):  # one two-view triangulation per keyframe pair
        sel = np.flatnonzero(ok & (pair_id == key))
        a, b = int(k1[sel[0]]), int(k2[sel[0]])
        pts, depth = triangulate_pairs(
            rays[first[sel]], rays[last[sel]], invert(world_from_rig[b]) @ world_from_rig[a]
        )
        front = (depth[:, 0] > 0) & (depth[:, 1] > 0)
        ok[sel[~front]] = False
        X[sel[front]] = pts[front] @ R[a].T + C[a]
    track = np.repeat(np.arange(len(start)), np.diff(np.r_[start, len(frames)]))
    on = np.flatnonzero(ok[track])  # the observations of the tracks triangulated
    valid = np.zeros(len(frames), bool)
    err = np.zeros(len(frames))
    if len(on):
        q = np.einsum("nji,nj->ni", R[frames[on]], X[track[on]] - C[frames[on]])
        px, valid[on] = camera.project(q)
        err[on] = np.linalg.norm(px - obs[on], axis=1)
    seen = np.minimum.reduceat(valid, start)
    worst = np.maximum.reduceat(np.where(valid, err, 0.0), start)
    return X, ok & seen & ~(worst > config.max_reprojection_px)


def _stack_anchors(
    anchors: list[tuple[int, int, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(L,) keyframes a and b, (L, 3) laser points in rig a and (L, 2) pixels in b of all anchors."""
    if not anchors:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2))
    aa = np.concatenate([np.full(len(q), a) for a, _, q, _ in anchors])
    ab = np.concatenate([np.full(len(q), b) for _, b, q, _ in anchors])
    aq = np.concatenate([q for *_, q, _ in anchors])
    apx = np.concatenate([p for *_, p in anchors])
    return aa, ab, aq, apx


def build_problem(
    camera: CameraModel,
    world_from_rig: np.ndarray,
    pixels: list[np.ndarray],
    rays_in_rig: list[np.ndarray],
    pair_matches: list[tuple[int, int, np.ndarray]],
    anchors: list[tuple[int, int, np.ndarray, np.ndarray]],
    config: BundleConfig,
) -> BundleProblem:
    """Feature tracks from pairwise matches, triangulated with the initial poses.

    Args:
        world_from_rig: (K, 4, 4) initial keyframe poses.
        pixels, rays_in_rig: per keyframe, (N_k, 2) feature pixels and (N_k, 3) unit rays.
        pair_matches: (a, b, (M, 2) feature indices in a and b) of RANSAC inliers.
        anchors: (a, b, (L, 3) laser points in rig a, (L, 2) matched pixels in b).
    """
    feature_point = [np.full(len(p), -1) for p in pixels]
    tracks = _select_tracks(pixels, pair_matches, config.max_tracks)
    aa, ab, aq, apx = _stack_anchors(anchors)
    if tracks:
        frames = np.concatenate([f for f, _ in tracks]).astype(int)
        local = np.concatenate([li for _, li in tracks]).astype(int)
        start = np.r_[0, np.cumsum([len(f) for f, _ in tracks])[:-1]].astype(int)
        offset = np.r_[0, np.cumsum([len(p) for p in pixels])].astype(int)
        flat = offset[frames] + local
        obs = np.concatenate(pixels)[flat].astype(float)
        X, kept = _triangulate_tracks(
            camera, world_from_rig, frames, np.concatenate(rays_in_rig)[flat], obs, start, config
        )
        track = np.repeat(np.arange(len(tracks)), np.diff(np.r_[start, len(frames)]))
        point_of = np.cumsum(kept) - 1  # each kept track's point, in track order
        seen = kept[track]
        for k in range(len(pixels)):
            mine = seen & (frames == k)
            feature_point[k][local[mine]] = point_of[track[mine]]
        if kept.any():
            return BundleProblem(
                world_from_rig, X[kept], frames[seen], point_of[track[seen]], obs[seen],
                aa, ab, aq, apx, feature_point,
            )
    return BundleProblem(world_from_rig, np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int),
                         np.zeros((0, 2)), aa, ab, aq, apx, feature_point)


def cross_rows(q: np.ndarray, r0: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """(N, 3) ``np.cross(q, r)`` of (N, 3) ``q`` and the rows of r given as its three
    (N,) contiguous columns, to the bit (the same products and differences), without
    np.cross's axis handling (a third of the resection's residual)."""
    out = np.empty((len(q), 3))
    q0, q1, q2 = q[:, 0], q[:, 1], q[:, 2]
    np.subtract(q1 * r2, q2 * r1, out=out[:, 0])
    np.subtract(q2 * r0, q0 * r2, out=out[:, 1])
    np.subtract(q0 * r1, q1 * r0, out=out[:, 2])
    return out


def resect_rays(
    rays_in_rig: np.ndarray, points_in_world: np.ndarray, world_from_rig_init: np.ndarray,
    max_angle_rad: float = np.radians(2.0),
) -> np.ndarray:
    """Pose of a rig whose rays see known world points (omni-directional resection).

    Minimises the robust angle between each ray and the direction to its point, from
    an initial pose (the nearest keyframe's), then once more on the rays within
    ``max_angle_rad`` (unverified matches, wrong tracks). Works for rays in every direction.

    Args:
        rays_in_rig: (M, 3) unit rays of the rig's features.
        points_in_world: (M, 3) the points they see, mm.
        world_from_rig_init: (4, 4) start.
        max_angle_rad: inlier bound of the final check (the soft-L1 scale is a fifth of it).

    Returns:
        world_from_rig: (4, 4).

    Raises:
        ReconstructionError: fewer than 6 consistent rays after the fit.
    """
    p0 = _poses_to_params(world_from_rig_init[None])[0]

    r0, r1, r2 = (np.ascontiguousarray(rays_in_rig[:, i], float) for i in range(3))

    def residual(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        q = points_in_world @ R.T + x[3:]
        q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-9)
        return cross_rows(q, r0, r1, r2).ravel()  # |sin angle| per axis

    def solve(keep: np.ndarray, x0: np.ndarray):
        def res(x: np.ndarray) -> np.ndarray:
            return residual(x).reshape(-1, 3)[keep].ravel()

        return least_squares(res, x0, loss="soft_l1", f_scale=0.2 * max_angle_rad, x_scale="jac")

    keep = np.ones(len(points_in_world), bool)
    sol = solve(keep, p0)
    ang = np.linalg.norm(residual(sol.x).reshape(-1, 3), axis=1)
    inl = ang < max_angle_rad
    if inl.sum() >= 6 and not inl.all():
        # Refit on the consistent rays only (unverified matches, a wrong track).
        keep = inl
        sol = solve(keep, sol.x)
        ang = np.linalg.norm(residual(sol.x).reshape(-1, 3), axis=1)
    if np.sum(ang < max_angle_rad) < 6:
        raise ReconstructionError("resection: fewer than 6 consistent rays")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[3:]
    return invert(T)


def keyframe_windows(n_keyframes: int, size: int, overlap: int) -> list[tuple[int, int, int]]:
    """Consecutive windows of a long run's keyframes for bundle adjustment.

    Each window ``(start, end, fixed)`` adjusts keyframes ``start .. end - 1``; its first
    ``fixed`` keyframes are the last ones of the window before (already adjusted, held
    fixed: they tie the window to the run) or, in the first window, keyframe 0 (the
    world). Every keyframe is adjusted in exactly one window, so the cost is linear in
    the run's length. ``size`` <= 0 or a run of at most 1.25 ``size`` keyframes: one
    window (the global adjustment).

    Raises:
        ConfigError: ``overlap`` not in 1 .. size - 2.
    """
    if size <= 0 or n_keyframes <= size + size // 4:
        return [(0, n_keyframes, 1)]
    if not 1 <= overlap <= size - 2:
        raise ConfigError("sfm.bundle.window_overlap", f"must be 1 .. window_keyframes - 2, got {overlap}")
    out = [(0, size, 1)]
    while out[-1][1] < n_keyframes:
        start = out[-1][1] - overlap
        end = min(n_keyframes, start + size)
        if n_keyframes - end < size // 4:  # no sliver of a last window: this one takes it
            end = n_keyframes
        out.append((start, end, overlap))
    return out

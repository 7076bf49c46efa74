"""The laser ring as a constraint on the rig's path across the pipe.

Every frame's laser ring is the pipe's cross-section in the laser plane; the centre of
its ellipse is where the pipe's axis pierces the plane, in the rig frame (a tilted
cylinder cuts the plane in an ellipse whose centre is on the axis). Carried into the
world by the frame's pose, ``X_k = world_from_rig_k @ c_k``, the centres of
consecutive keyframes lie on the pipe's axis: a smooth curve. The bundle adjustment
(:mod:`omnipipe.sfm.bundle`) gets one pair of rows per keyframe k between two others
a < k < b: the part of ``X_k - ((1 - f) X_a + f X_b)`` across the axis, per its sigma
(f: k's fraction of the way from a to b along the axis). Sideways drift and a turn
of the rig that the features leave loose (a few dozen matches, a large pipe's far
wall) then cannot accumulate: Hansen et al. (IJRR 2015) found pipe-shape constraints
essential for visual odometry in pipes. The rows hold the points where the axis pierces
the keyframes' laser planes, not the rigs' turn about them: a keyframe turned by an
angle about its ring's centre swings its rig across the axis by the plane's distance
times the angle (90 mm and 1.5 deg: 2.4 mm) and leaves every centre, and so every row,
where it was. That turn is left to the features; the ellipse's shape is too weak to
hold it (a tilt changes the ratio of its axes by 1 / cos, second order, and the pipe's
own ovality adds to that ratio).

Sigmas are measured, not assumed: a centre's 1-sigma is :data:`CENTRE_SIGMA_GAIN`
times the robust scatter of its ring's points about the fitted ellipse (per point,
mm), which covers the robustness bench's rings against the truth (the centre's error
is not the scatter over sqrt(N): on a large pipe at 640x480 the range errors vary
smoothly around the ring, and a 940 mm pipe's centres scatter 1.6 mm about the axis
with the true poses, too much to place its rigs); a bend adds the chord's sagitta at k,
``f (1 - f) L theta / 2`` (L the chord a -> b, theta the rigs' turn between a and b).

The axis is smooth only within a pipe section: at a joint the next section's axis is
displaced (its offset), and a lateral's hole pulls its rings' ellipse centres. Such a
step is in the rings' positions in their rigs, not in the rigs' path, so a triple whose
departure from the chord comes from the centres moving in the rigs (:func:`axis_rows`)
is left out: held to it, the adjustment would bend the rigs' path to erase the offset
(the features bench's seed 22: a 5.9 mm joint offset gone from the model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Fewer points than this make no centre.
MIN_RING_POINTS = 30
# Robust passes of the ellipse fit and the outlier bound (robust sigmas, and a floor, mm).
RING_PASSES = 3
RING_OUTLIER_SIGMAS = 3.0
RING_OUTLIER_FLOOR_MM = 0.2
# A centre's 1-sigma per robust sigma of its points about the ellipse (mm per mm): the
# centres' scatter about the axis with the true poses is 0.2-0.8 of it on the robustness
# bench's rings (seeds 31, 1, 18, 37), and with 0.8 the rows of 10 seeds' true keyframe
# poses lie 98 % within 1 sigma, all within 2: conservative, so only a clear kink triggers.
CENTRE_SIGMA_GAIN = 0.8
# Floor of a centre's sigma, mm.
CENTRE_SIGMA_FLOOR_MM = 0.005
# The rows are added (the adjustment run again) only when the adjustment without them
# left a keyframe's centre this many of its sigmas off its neighbours' chord.
RING_TRIGGER_SIGMAS = 3.0
# Keyframes a and b closer than this along the axis make no row (no direction), mm.
MIN_CHORD_MM = 0.5
# A triple whose centres leave the chord by at least this (mm) and RING_TRIGGER_SIGMAS of
# its sigma through the rings' own positions in the rigs (the rigs' path straight there)
# makes no row: the pipe's axis itself steps between its keyframes (a joint's offset:
# the features bench's offset joints step 2-7 mm) or a hole pulls a ring's centre.
PIPE_STEP_MIN_MM = 1.0


@dataclass(frozen=True)
class RingCentre:
    """Where the pipe's axis pierces a frame's laser plane.

    Attributes:
        centre_in_rig: (3,) the ring ellipse's centre in the rig frame, mm.
        sigma_mm: its 1-sigma across the axis, mm.
    """

    centre_in_rig: np.ndarray
    sigma_mm: float


def fit_ring_centre(points_in_rig: np.ndarray) -> RingCentre | None:
    """The centre of one frame's laser ring ((N, 3) points in the rig, mm) and its sigma.

    A general conic ``a x^2 + b xy + c y^2 + d x + e y = 1`` is fitted in the plane's
    own 2-D basis (the points' principal directions); points beyond
    :data:`RING_OUTLIER_SIGMAS` robust sigmas of it (defects, water, spurious peaks)
    are dropped over :data:`RING_PASSES` passes. None with fewer than
    :data:`MIN_RING_POINTS` points or no ellipse.
    """
    fit = robust_ellipse_centre(points_in_rig, MIN_RING_POINTS, RING_OUTLIER_FLOOR_MM)
    if fit is None or not math.isfinite(fit[1]):
        return None
    return RingCentre(fit[0], max(CENTRE_SIGMA_GAIN * fit[1], CENTRE_SIGMA_FLOOR_MM))


def robust_ellipse_centre(
    points_in_rig: np.ndarray, min_points: int, floor_mm: float
) -> tuple[np.ndarray, float] | None:
    """((3,) the ring's ellipse centre in the rig (mm), the radial residuals' robust
    sigma (mm)) of (N, 3) ring points: the conic fit of :func:`fit_ring_centre`, points
    beyond max(:data:`RING_OUTLIER_SIGMAS` sigmas, ``floor_mm``) dropped over
    :data:`RING_PASSES` passes. None with fewer than ``min_points`` points (kept) or no
    ellipse."""
    p = np.asarray(points_in_rig, float)
    if p.ndim != 2 or len(p) < min_points:
        return None
    mean = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - mean, full_matrices=False)
    xy = np.column_stack([(p - mean) @ vt[0], (p - mean) @ vt[1]])
    keep = np.ones(len(xy), bool)
    centre, mad = None, math.inf
    for _ in range(RING_PASSES):
        if keep.sum() < min_points:
            return None
        x, y = xy[keep, 0], xy[keep, 1]
        s, *_ = np.linalg.lstsq(np.column_stack([x * x, x * y, y * y, x, y]), np.ones(len(x)), rcond=None)
        q = np.array([[s[0], s[1] / 2], [s[1] / 2, s[2]]])
        if np.linalg.det(q) <= 0 or s[0] <= 0:
            return None
        centre = np.linalg.solve(2 * q, -s[3:5])
        d = xy - centre
        k_c = 1.0 + float(centre @ q @ centre)  # the conic centred: d^T q d = k_c
        r = np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", d, q, d), 0) / k_c)  # 1 on the ellipse
        res = (r - 1.0) * math.sqrt(k_c / np.linalg.eigvalsh(q).mean())  # mm
        mad = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep]))))
        keep = np.abs(res) <= max(RING_OUTLIER_SIGMAS * mad, floor_mm)
    if centre is None:
        return None
    return mean + centre[0] * vt[0] + centre[1] * vt[1], mad


@dataclass
class AxisRows:
    """The bundle adjustment's ring rows (T triples of keyframes a < k < b).

    Attributes:
        kf: (T, 3) keyframes (a, k, b), counted from the problem's first.
        centres_in_rig: (T, 3, 3) the ring centres of a, k and b in their rigs, mm.
        fraction: (T,) f: k's fraction of the way from a to b along the axis.
        across: (T, 2, 3) two unit directions across the axis (world), fixed at the start.
        sigma_mm: (T,) each row pair's 1-sigma, mm.
    """

    kf: np.ndarray
    centres_in_rig: np.ndarray
    fraction: np.ndarray
    across: np.ndarray
    sigma_mm: np.ndarray

    @staticmethod
    def empty() -> AxisRows:
        return AxisRows(np.zeros((0, 3), int), np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 2, 3)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.kf)


def axis_rows(world_from_kf: np.ndarray, centres: list[RingCentre | None]) -> AxisRows:
    """Ring rows for every keyframe with a centre between the nearest two others that
    have one (``world_from_kf`` (K, 4, 4) the start poses, mm; ``centres`` per keyframe).
    The fraction f, the directions across the axis and the bend's sagitta allowance are
    taken from the start poses."""
    have = [(k, c) for k, c in enumerate(centres) if c is not None]
    rows: list[tuple] = []
    for (a, ca), (k, ck), (b, cb) in zip(have, have[1:], have[2:], strict=False):
        X = [world_from_kf[j, :3, :3] @ c.centre_in_rig + world_from_kf[j, :3, 3] for j, c in ((a, ca), (k, ck), (b, cb))]
        chord = X[2] - X[0]
        length = float(np.linalg.norm(chord))
        if length < MIN_CHORD_MM:
            continue
        u = chord / length
        f = float(np.clip((X[1] - X[0]) @ u / length, 0.0, 1.0))
        e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        turn = _turn(world_from_kf[a], world_from_kf[b])
        sagitta = f * (1.0 - f) * length * turn / 2.0
        sigma = math.sqrt(ck.sigma_mm**2 + ((1 - f) * ca.sigma_mm) ** 2 + (f * cb.sigma_mm) ** 2 + sagitta**2)
        if _pipe_steps(world_from_kf[[a, k, b]], ck.centre_in_rig, X, f, np.array([e1, np.cross(u, e1)]), sigma):
            continue
        rows.append(((a, k, b), (ca.centre_in_rig, ck.centre_in_rig, cb.centre_in_rig), f, (e1, np.cross(u, e1)), sigma))
    if not rows:
        return AxisRows.empty()
    return AxisRows(
        np.array([r[0] for r in rows], int),
        np.array([r[1] for r in rows], float),
        np.array([r[2] for r in rows], float),
        np.array([r[3] for r in rows], float),
        np.array([r[4] for r in rows], float),
    )


def _pipe_steps(
    world_from_akb: np.ndarray, centre_k: np.ndarray, X: list[np.ndarray], f: float, across: np.ndarray, sigma: float
) -> bool:
    """Whether a triple's centres ``X`` (world, mm) leave their chord (across the axis,
    ``across`` (2, 3)) through the rings' positions in the rigs rather than the rigs'
    path: the path of one point fixed in the rigs (k's centre, ``centre_k``) departs from
    its chord by at most half as much as the centres' own share, which is at least
    :data:`PIPE_STEP_MIN_MM` and :data:`RING_TRIGGER_SIGMAS` x ``sigma``."""
    P = np.einsum("jab,b->ja", world_from_akb[:, :3, :3], centre_k) + world_from_akb[:, :3, 3]
    weights = np.array([-(1.0 - f), 1.0, -f])
    path = float(np.linalg.norm(across @ (weights @ P)))
    rings = float(np.linalg.norm(across @ (weights @ np.array(X) - weights @ P)))
    return rings >= max(PIPE_STEP_MIN_MM, RING_TRIGGER_SIGMAS * sigma) and path <= 0.5 * rings


def _turn(world_from_a: np.ndarray, world_from_b: np.ndarray) -> float:
    """The angle between two rigs' orientations, rad."""
    c = (np.trace(world_from_a[:3, :3].T @ world_from_b[:3, :3]) - 1.0) / 2.0
    return math.acos(min(1.0, max(-1.0, c)))


def ring_offsets(world_from_kf: np.ndarray, rows: AxisRows) -> np.ndarray:
    """(T, 2) each row's centre of k off its neighbours' chord across the axis (mm), with
    the keyframe poses ``world_from_kf`` (K, 4, 4)."""
    k = rows.kf
    X = np.einsum("tjab,tjb->tja", world_from_kf[k][:, :, :3, :3], rows.centres_in_rig) + world_from_kf[k][:, :, :3, 3]
    coef = np.column_stack([-(1.0 - rows.fraction), np.ones(len(rows)), -rows.fraction])
    return np.einsum("tpi,ti->tp", rows.across, np.einsum("tj,tji->ti", coef, X))

"""The pipe's centreline from the measured rings, and pipe coordinates on it.

Each ring (one keyframe's light section) is a station. Around every station a
cylinder is fitted to the rings within ``window_mm`` along the axis (the piecewise
cylinder fit that follows bends); the station's centre is its ring centroid
projected onto that axis and its tangent is the axis. Arc length runs through the
station centres; the angle around the axis is measured from a frame (N, B, T)
parallel-transported from the reference rig frame's x axis, so "angle" means the
same thing all along a bent pipe, as the data contract asks.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from omnipipe.analysis.cylinder import Cylinder, basis, fit_cylinder
from omnipipe.errors import ReconstructionError
from omnipipe.executor import InlineExecutor, ordered_map
from omnipipe.progress import phase

AXIS_PRIOR_SIGMA_RAD = float(np.radians(1.0))
"""Spread of the pipe axis about the rig's z axis where the rig is (rad): the robot's head
tilts about a degree in the pipe (the simulator's ``tilt_deg`` 0.8)."""

_WEAK_PRIOR_RAD = float(np.radians(3.0))
"""A prior wider than this (rad) is not used: the station's tangent is the centres' line
alone, as without a prior."""

_CENTRE_NOISE_FLOOR_MM = 0.1
"""Least scatter (mm) assumed of the station centres about their line."""


@dataclass(frozen=True)
class Centreline:
    """Stations along the measured pipe (world frame, mm).

    Attributes:
        arc_mm: (K,) arc length of each station from the reference origin's
            projection (the contract's axial origin: the first frame's origin).
        centre: (K, 3) points on the axis.
        tangent: (K, 3) unit axis directions, pointing the way the robot travelled.
        normal, binormal: (K, 3) unit vectors; angle 0 along ``normal``, pi/2 along ``binormal``.
        radius_mm: (K,) radius of the cylinder fitted around each station.
        cylinders: the fitted cylinder of each station's window (without its
            ``residuals_mm``: empty).
    """

    arc_mm: np.ndarray
    centre: np.ndarray
    tangent: np.ndarray
    normal: np.ndarray
    binormal: np.ndarray
    radius_mm: np.ndarray
    cylinders: list[Cylinder]

    @classmethod
    def straight(cls, arc_mm: np.ndarray, radius_mm: float | np.ndarray) -> Centreline:
        """A straight centreline along world z through the stations ``arc_mm`` (K,) mm
        (normal x, binormal y), of radius ``radius_mm`` (a number or (K,) mm): a
        synthetic pipe's."""
        k = len(arc_mm)
        z = np.tile([0.0, 0.0, 1.0], (k, 1))
        return cls(
            arc_mm, arc_mm[:, None] * z, z, np.tile([1.0, 0.0, 0.0], (k, 1)),
            np.tile([0.0, 1.0, 0.0], (k, 1)), np.full(k, radius_mm), [],
        )

    def straightness_mm(self) -> float:
        """Largest distance of a station centre from the best straight line through them
        (the line's direction from the centres' thin SVD: no (K, K) factor, 46 MB at 2,400
        stations)."""
        c = self.centre - self.centre.mean(axis=0)
        if len(c) < 3:
            return 0.0
        _, _, vt = np.linalg.svd(c, full_matrices=False)
        return float(np.max(np.linalg.norm(c - np.outer(c @ vt[0], vt[0]), axis=1)))

    def coordinates(
        self, points_in_world: np.ndarray, station: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pipe coordinates of points measured at known stations, computed
        :data:`COORDINATE_BLOCK` points at a time (each point's numbers are those of the
        whole-array formula: the temporaries stay a block's, not the run's).

        Args:
            points_in_world: (N, 3) mm.
            station: (N,) station index of each point (its ring).

        Returns:
            sigma_mm: (N,) arc length along the centreline.
            rho_mm: (N,) distance from the axis.
            theta_rad: (N,) angle around the axis in [-pi, pi), from N towards B.
        """
        station = np.asarray(station)
        n = len(station)
        out = (np.empty(n), np.empty(n), np.empty(n))
        for a in range(0, n, COORDINATE_BLOCK):
            b = min(a + COORDINATE_BLOCK, n)
            for whole, part in zip(out, self._coordinates_block(points_in_world[a:b], station[a:b]), strict=True):
                whole[a:b] = part
        return out

    def _coordinates_block(
        self, points_in_world: np.ndarray, station: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`coordinates` of one block of points, whole."""
        q = points_in_world - self.centre[station]
        t = self.tangent[station]
        along = np.einsum("ij,ij->i", q, t)
        perp = q - along[:, None] * t
        rho = np.linalg.norm(perp, axis=1)
        theta = np.arctan2(
            np.einsum("ij,ij->i", perp, self.binormal[station]),
            np.einsum("ij,ij->i", perp, self.normal[station]),
        )
        return self.arc_mm[station] + along, rho, theta


COORDINATE_BLOCK = 1 << 16
"""Points per block of :meth:`Centreline.coordinates` (its temporaries, about 150 bytes a
point, are a block's: 10 MB)."""


def recentred(
    line: Centreline,
    offsets: np.ndarray,
    reference_from_world: np.ndarray,
    half_span_mm: float,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    axis_prior: AxisPrior | None = None,
) -> Centreline:
    """The centreline through corrected station centres.

    Args:
        line: the piecewise fit.
        offsets: (K, 2) each station's section centre in its (normal, binormal) plane (mm):
            the order-1 terms of its wall profile.
        reference_from_world: as for :func:`fit_centreline`.
        half_span_mm: the tangent at a station is the direction of the corrected
            centres within this distance (on its side of every break).
        breaks: planes (point, normal; world mm) between separately fitted sections.
        axis_prior: the prior of the tangents (:func:`rig_axis_prior`,
            :func:`local_tangents`); None: the centres' line alone.

    A short window's cylinder can tilt to mimic an oval section (an oblique cut of a
    circular cylinder is an ellipse: 6 % ovality ~ 20 deg), which shifts its station's
    projected centre; each ring's own section centre has no such freedom.
    """
    off = np.asarray(offsets, float)
    centre = line.centre + off[:, :1] * line.normal + off[:, 1:2] * line.binormal
    side = np.array([np.sign((line.centre - p) @ n) for p, n in breaks]).reshape(len(breaks), len(centre))
    tangent = local_tangents(centre, line.tangent, half_span_mm, side, prior=axis_prior)
    steps = np.einsum("ij,ij->i", np.diff(centre, axis=0), tangent[1:] + tangent[:-1])
    steps /= np.maximum(np.linalg.norm(tangent[1:] + tangent[:-1], axis=1), 1e-12)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    arc, normals = _referenced(arc, centre, tangent, reference_from_world)
    return Centreline(
        arc, centre, tangent, normals, np.cross(tangent, normals), line.radius_mm, line.cylinders
    )


def _referenced(
    arc: np.ndarray, centre: np.ndarray, tangent: np.ndarray, reference_from_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The stations' arc lengths (K,) shifted to the reference's axial origin (the
    reference origin projected on the nearest station's axis), and their (K, 3) unit
    normals: the reference x axis (angle 0), transported along the stations."""
    world_from_reference = np.linalg.inv(reference_from_world)
    origin, x_ref = world_from_reference[:3, 3], world_from_reference[:3, 0]
    nearest = int(np.argmin(np.linalg.norm(centre - origin, axis=1)))
    arc = arc - (arc[nearest] + (origin - centre[nearest]) @ tangent[nearest])
    normals = np.empty_like(tangent)
    n = x_ref - (x_ref @ tangent[nearest]) * tangent[nearest]
    normals[nearest] = n / np.linalg.norm(n)
    for order in (range(nearest + 1, len(tangent)), range(nearest - 1, -1, -1)):
        prev = nearest
        for k in order:
            n = normals[prev] - (normals[prev] @ tangent[k]) * tangent[k]
            normals[k] = n / np.linalg.norm(n)
            prev = k
    return arc, normals


def _nearest_usable(usable: list[int], full: int) -> np.ndarray:
    """(full,) for each ring, the slot in ``usable`` of its nearest usable ring (itself
    when usable): rings too sparse for a station borrow their nearest neighbour's."""
    u = np.asarray(usable)
    k = np.arange(full)
    right = np.clip(np.searchsorted(u, k), 0, len(u) - 1)  # first usable >= k
    left = np.clip(right - 1, 0, len(u) - 1)
    # argmin takes the first (lower) of two equally near rings
    return np.where(np.abs(u[left] - k) <= np.abs(u[right] - k), left, right)


def fit_centreline(
    rings_in_world: Sequence[np.ndarray],
    axis_guess: np.ndarray,
    reference_from_world: np.ndarray,
    *,
    window_mm: float,
    loss_scale_mm: float,
    max_points: int = 6000,
    executor: Executor | None = None,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> Centreline:
    """Piecewise cylinder fit along the rings; the stations' fits run on ``executor``
    (:mod:`omnipipe.executor`; None: here), in order, the same wherever they run.

    Args:
        rings_in_world: K arrays (M_k, 3) of ring points in the world frame, in time order.
        axis_guess: (K, 3) rough axis direction at each station (the rig's z axis in the world).
        reference_from_world: (4, 4) pose whose origin is the axial origin and whose x axis
            is angle 0 (the first registered frame's rig frame, inverted).
        window_mm: axial length of the rings used for each station's cylinder.
        loss_scale_mm: soft-L1 scale of the cylinder fits.
        max_points: points per fit (evenly subsampled; the fit is linear in their number).
        breaks: planes (point, normal; world mm) no station's window reaches across: the
            sections either side of an offset joint are fitted separately.

    Raises:
        ReconstructionError: fewer than 2 rings with enough points.
    """
    usable = [k for k, r in enumerate(rings_in_world) if len(r) >= 12]
    if len(usable) < 2:
        raise ReconstructionError(
            f"only {len(usable)} ring(s) with enough laser points: cannot fit the pipe's axis"
        )
    centroid = np.array([rings_in_world[k].mean(axis=0) for k in usable])
    axes = np.asarray(axis_guess, float)[usable]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    # (B, U) the side of each break each usable ring lies on
    side = np.array([np.sign((centroid - p) @ n) for p, n in breaks]).reshape(len(breaks), len(usable))
    windows = _windows(rings_in_world, usable, centroid, axes, side, window_mm, loss_scale_mm, max_points)
    fits = ordered_map(executor or InlineExecutor(), _fit_window, windows)
    tick = phase("centreline", len(usable))
    cylinders: list[Cylinder] = []
    centres, tangents = [], []
    for i, cyl in enumerate(fits):
        tick(i + 1)
        tangent = cyl.axis if cyl.axis @ axes[i] > 0 else -cyl.axis
        centres.append(cyl.point + ((centroid[i] - cyl.point) @ tangent) * tangent)
        tangents.append(tangent)
        cylinders.append(cyl)
    centre = np.array(centres)
    # In a bend a window's cylinder axis is a chord; the tangent at a station is better
    # the direction of the station centres around it (a short line fit, on its side of
    # every break).
    tangent = local_tangents(centre, np.array(tangents), 0.25 * window_mm, side)
    # Arc length through the centres, each step measured along the mean tangent.
    steps = np.einsum("ij,ij->i", np.diff(centre, axis=0), tangent[1:] + tangent[:-1])
    steps /= np.linalg.norm(tangent[1:] + tangent[:-1], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(steps)])
    arc, normals = _referenced(arc, centre, tangent, reference_from_world)
    binormals = np.cross(tangent, normals)
    pick = _nearest_usable(usable, len(rings_in_world))
    radii = np.array([c.radius_mm for c in cylinders])
    return Centreline(
        arc[pick], centre[pick], tangent[pick], normals[pick], binormals[pick], radii[pick],
        [cylinders[i] for i in pick],
    )


def _windows(
    rings_in_world: Sequence[np.ndarray],
    usable: list[int],
    centroid: np.ndarray,
    axes: np.ndarray,
    side: np.ndarray,
    window_mm: float,
    loss_scale_mm: float,
    max_points: int,
) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """(points, axis guess, loss scale) of each station's window, made as needed: the
    usable rings within ``window_mm`` / 2 along the station's axis guess and on its side
    of every break (``side``: (B, U) signs)."""
    slot_of = {k: j for j, k in enumerate(usable)}
    for i in range(len(usable)):
        along = (centroid - centroid[i]) @ axes[i]
        same = np.all(side == side[:, i : i + 1], axis=0)
        members = [usable[j] for j in np.flatnonzero((np.abs(along) <= 0.5 * window_mm) & same)]
        pts = np.concatenate([rings_in_world[j] for j in members])
        if len(pts) > max_points:
            pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(int)]
        guess = axes[i] if len(members) < 3 else np.mean(axes[[slot_of[j] for j in members]], axis=0)
        yield pts, guess, loss_scale_mm


def _fit_window(window: tuple[np.ndarray, np.ndarray, float]) -> Cylinder:
    """Executor task: :func:`fit_cylinder` of one station's (points, axis guess, loss scale),
    its ``residuals_mm`` dropped (empty): nothing reads them, and kept for every station
    they were the analysis' largest holding (a window's points, 8 bytes each: 12 KB a
    frame on the paper run at 400x300, 1.2 GB over 100,000 frames)."""
    pts, guess, loss_scale_mm = window
    return replace(fit_cylinder(pts, guess, loss_scale_mm=loss_scale_mm), residuals_mm=_NONE)


_NONE = np.zeros(0)


def local_tangents(
    centre: np.ndarray,
    fallback: np.ndarray,
    half_span_mm: float,
    side: np.ndarray | None = None,
    prior: AxisPrior | None = None,
    curved: bool = False,
) -> np.ndarray:
    """(K, 3) unit directions of the centres within ``half_span_mm`` of each station (and,
    with ``side`` ((B, K) signs), on its side of every break); ``curved``: each the slope
    at its station of a quadratic through those centres (:func:`_curved_direction`), not
    their line's.

    With a ``prior`` at most ``_WEAK_PRIOR_RAD`` wide at a station, its direction is the
    line fit of the centres with that Gaussian prior on its slope
    (:func:`_ridge_direction`): a short run's centres (a few rings over 20-60 mm, each
    off the axis by a joint's offset, a taper or the wall noise) cannot tilt it by degrees.
    """
    out = fallback.copy()
    # The centres near each one from a tree (then the exact test on those): linear in the run.
    tree = cKDTree(centre) if len(centre) else None
    for i in range(len(centre)):
        cand = np.sort(np.asarray(tree.query_ball_point(centre[i], half_span_mm * (1 + 1e-9) + 1e-9), int))
        near = cand[np.linalg.norm(centre[cand] - centre[i], axis=1) <= half_span_mm]
        if side is not None and len(side):
            near = near[np.all(side[:, near] == side[:, i : i + 1], axis=0)]
        if prior is not None and prior.sigma_rad[i] <= _WEAK_PRIOR_RAD:
            d = _ridge_direction(centre[near], prior.direction[i], float(prior.sigma_rad[i]))
            out[i] = d if d @ fallback[i] > 0 else -d
            continue
        if len(near) < 3:
            continue
        c = centre[near] - centre[near].mean(axis=0)
        _, sv, vt = np.linalg.svd(c, full_matrices=False)
        if sv[0] < 1e-6 or (len(sv) > 1 and sv[1] > 0.5 * sv[0]):
            continue  # no clear direction: the stations are too close together
        d = _curved_direction(centre[near] - centre[i], vt[0]) if curved else vt[0]
        out[i] = d if d @ fallback[i] > 0 else -d
    return out


def _curved_direction(rel: np.ndarray, line: np.ndarray) -> np.ndarray:
    """(3,) unit tangent at the station of centres ``rel`` (M, 3) (mm, relative to the
    station's own) whose line fit runs along the unit ``line`` (3,): the slope at the
    station of a quadratic fitted across the line (x(s) = x0 + x1 s + x2 s^2, s along
    it). Around a station with centres on both sides alike it is the line's; at a run's
    end (centres on one side only) a line through a bend's centres is their chord,
    half the turn over the span behind the curve's tangent there (read as the turn
    ending before the run's end: benchmarks/RESULTS.md, ana22). The line's direction
    where the centres span fewer than three distinct positions."""
    s = rel @ line
    if len(np.unique(np.round(s, 3))) < 3:
        return line
    perp = rel - np.outer(s, line)
    A = np.column_stack([np.ones_like(s), s, s * s])
    coef, *_ = np.linalg.lstsq(A, perp, rcond=None)
    d = line + coef[1]
    return d / np.linalg.norm(d)


@dataclass(frozen=True)
class BendFit:
    """A bend measured on the centreline (:func:`fit_bend`): straight, turning at a
    constant rate, straight again.

    Attributes:
        start_mm, end_mm: arc length where the turning starts and stops.
        start_sigma_mm, end_sigma_mm: their 1-sigma (mm).
        turn_rad, turn_sigma_rad: the angle the tangent turns between them, 1-sigma.
        radius_mm, radius_sigma_mm: (end - start) / turn and its 1-sigma.
        truncated: the turning reaches the first or last station (it may go on).
    """

    start_mm: float
    start_sigma_mm: float
    end_mm: float
    end_sigma_mm: float
    turn_rad: float
    turn_sigma_rad: float
    radius_mm: float
    radius_sigma_mm: float
    truncated: bool


def bend_angles(tangent: np.ndarray) -> np.ndarray:
    """(K,) unwrapped angle (rad) of (K, 3) unit tangents in the plane they turn in (the
    plane through the origin nearest to all of them), from the first one's direction."""
    t = np.asarray(tangent, float)
    _, _, vt = np.linalg.svd(t, full_matrices=False)
    n = vt[-1]
    e1 = t[0] - (t[0] @ n) * n
    e1 /= max(float(np.linalg.norm(e1)), 1e-12)
    e2 = np.cross(n, e1)
    return np.unwrap(np.arctan2(t @ e2, t @ e1))


def fit_bend(
    arc_mm: np.ndarray, tangent: np.ndarray, guess: tuple[float, float], correlated: float = 1.0
) -> BendFit | None:
    """Straight - bend - straight fit of the tangent's turn along the centreline.

    The tangent's angle in its plane of turning (:func:`bend_angles`) is modelled as
    phi(s) = phi0 + turn * clip((s - a) / (b - a), 0, 1): constant before ``a`` and after
    ``b``, turning at a constant rate (radius (b - a) / turn) between. A robust (soft-L1)
    least-squares fit from ``guess`` (a, b). The piecewise fits' tangents are smoothed
    symmetrically along the arc, which rounds the kinks but does not move them.

    Args:
        arc_mm: (K,) arc length of the stations in the stretch to fit (ascending).
        tangent: (K, 3) their unit tangents.
        guess: start (a, b) of the turning (mm).
        correlated: how many neighbouring stations share each tangent's information
            (the tangent fits' span over the station spacing): the covariance is scaled
            by it.

    Returns:
        The fit, or None with fewer than 5 stations or a failed fit.
    """
    s = np.asarray(arc_mm, float)
    if len(s) < 5:
        return None
    phi = bend_angles(tangent)
    lo, hi = float(s[0]), float(s[-1])

    def model(x: np.ndarray) -> np.ndarray:
        a, b, phi0, turn = x
        return phi0 + turn * np.clip((s - a) / max(b - a, 1e-6), 0.0, 1.0)

    a0, b0 = max(min(guess), lo), min(max(guess), hi)
    if b0 - a0 < 1e-3:
        return None
    inside = (s >= a0) & (s <= b0)
    if not inside.any() or abs(_start(s, phi, a0, b0)[3]) < 1e-6:
        return None
    noise = max(float(np.std(np.diff(phi[~inside]))) / math.sqrt(2.0) if (~inside).sum() > 2 else _ramp_noise(s, phi), 1e-4)
    # From the guess and from the stations' quartiles (a kink the guess spans, such as
    # a missed joint's offset swinging the tangents, can hold the fit from one start in
    # a degenerate minimum): the lowest robust cost.
    sol = None
    for a_i, b_i in _bend_starts(s, (a0, b0)):
        got = least_squares(
            lambda x: (model(x) - phi) / noise, _start(s, phi, a_i, b_i), loss="soft_l1",
            bounds=([lo, lo, -np.inf, -np.inf], [hi, hi, np.inf, np.inf]),
            x_scale=[10.0, 10.0, 0.01, 0.01],
        )
        if got.success and got.x[1] - got.x[0] > 0 and (sol is None or got.cost < sol.cost - 1e-9):
            sol = got
    if sol is None:
        return None
    a, b, _, turn = sol.x
    if b - a <= 0 or abs(turn) < 1e-6:
        return None
    res = (model(sol.x) - phi) / noise
    dof = max(len(s) - 4, 1)
    var = float(res @ res) / dof * noise**2 * max(correlated, 1.0)
    edge = 0.5 * _spacing(s)
    # An end at the first / last station (the turning may go on past it) is no parameter
    # the stations measure: with none beyond it, it trades against phi0 / the turn. The
    # covariance is the others' with it held there (the turn: the run's part).
    free = np.array([a > lo + edge, b < hi - edge, True, True])
    cov = np.zeros((4, 4))
    cov[np.ix_(free, free)] = _pinv_cov(sol.jac[:, free] * noise, var)
    turn = abs(float(turn))
    sa, sb, st = (math.sqrt(max(cov[i, i], 0.0)) for i in (0, 1, 3))
    radius = (b - a) / turn
    # d radius = (db - da) / turn - radius dturn / turn
    g = np.array([-1.0 / turn, 1.0 / turn, 0.0, -math.copysign(radius / turn, sol.x[3])])
    sr = math.sqrt(max(float(g @ cov @ g), 0.0))
    return BendFit(
        start_mm=float(a), start_sigma_mm=math.hypot(sa, edge), end_mm=float(b),
        end_sigma_mm=math.hypot(sb, edge), turn_rad=turn, turn_sigma_rad=st,
        radius_mm=float(radius), radius_sigma_mm=sr,
        truncated=bool(a <= lo + edge or b >= hi - edge),
    )


def _ramp_noise(s: np.ndarray, phi: np.ndarray) -> float:
    """Robust 1-sigma (rad) of tangent angles ``phi`` (K,) at arcs ``s`` (K,) mm
    (ascending) about a line through their neighbours: each station's angle against the
    straight interpolation between the stations either side (the stations at one arc,
    a rest's, within ``_SAME_ARC_MM``, taken once), 1.4826 x the median absolute
    difference over its sigma in units of the noise (sqrt(1 + w1^2 + w2^2)). A bend's steady turn is such a line; its
    two kinks weigh nothing in the median. The noise of a bend fit whose stretch has no
    two straight stations to measure it on (the turning spans it, both ends truncated):
    with the tiny floor in its place the soft-L1 loss held every station an outlier and
    the fit's covariance went singular."""
    first = _places(s)
    u, p = s[first], phi[first]
    if len(u) < 3:
        return 0.0
    w2 = (u[1:-1] - u[:-2]) / (u[2:] - u[:-2])
    w1 = 1.0 - w2
    dev = (p[1:-1] - (w1 * p[:-2] + w2 * p[2:])) / np.sqrt(1.0 + w1**2 + w2**2)
    return 1.4826 * float(np.median(np.abs(dev)))


_SAME_ARC_MM = 0.1
"""Stations closer along the arc (mm) stand at one place (a rest's frames)."""


def _places(s: np.ndarray) -> np.ndarray:
    """Indices of the first station at each place along the ascending arcs ``s`` (K,) mm
    (the stations of a rest's frames stand within ``_SAME_ARC_MM``)."""
    return np.concatenate([[0], np.flatnonzero(np.diff(s) > _SAME_ARC_MM) + 1])


def _spacing(s: np.ndarray) -> float:
    """Median spacing (mm) of the places along the ascending arcs ``s`` (K,) (a rest's
    stations, at one place, counted once: else half the steps are 0)."""
    d = np.diff(s[_places(s)])
    return float(np.median(d)) if len(d) else 0.0


def _start(s: np.ndarray, phi: np.ndarray, a: float, b: float) -> np.ndarray:
    """(a, b, phi0, turn) to start the bend fit from: the angle's mean before ``a`` and
    after ``b`` (mm; the first / last station's when none lies there)."""
    phi0 = phi[s <= a].mean() if np.any(s <= a) else phi[0]
    return np.array([a, b, phi0, (phi[s >= b].mean() if np.any(s >= b) else phi[-1]) - phi0])


def _bend_starts(s: np.ndarray, guess: tuple[float, float]) -> list[tuple[float, float]]:
    """Starts (a, b) mm for the bend fit: ``guess`` first, then every ordered pair of the
    stations' quartile positions (0, 25, 50, 75, 100 %) at least two stations apart."""
    q = np.clip(np.percentile(s, [0.0, 25.0, 50.0, 75.0, 100.0]), s[0], s[-1])  # the fit's bounds
    out = [guess]
    for i in range(len(q)):
        for j in range(i + 1, len(q)):
            if q[j] > q[i] and int(np.sum((s >= q[i]) & (s <= q[j]))) >= 2 and (q[i], q[j]) != guess:
                out.append((float(q[i]), float(q[j])))
    return out


def _pinv_cov(jac: np.ndarray, var: float) -> np.ndarray:
    """(P, P) covariance var (J^T J)^-1 of a least-squares fit with Jacobian ``jac`` (N, P)."""
    return np.linalg.pinv(jac.T @ jac) * var


@dataclass(frozen=True)
class AxisPrior:
    """The pipe axis expected at each station from the robot's motion (world frame).

    Attributes:
        direction: (K, 3) unit directions.
        sigma_rad: (K,) their spread (rad).
    """

    direction: np.ndarray
    sigma_rad: np.ndarray


def rig_axis_prior(
    world_from_rig: np.ndarray, centre: np.ndarray, sigma_rad: float = AXIS_PRIOR_SIGMA_RAD
) -> AxisPrior:
    """The rig's z axis as the prior of the pipe axis at its own ring (the robot runs
    along the pipe).

    Args:
        world_from_rig: (K, 4, 4) the rig pose of each station's frame.
        centre: (K, 3) the station centres (world, mm).
        sigma_rad: the prior's spread where the rig is (its head's tilt in the pipe).

    The ring lies a lead L (mm, along z) from the rig, where the pipe may have turned:
    the spread grows by the turn the rig's z axis makes over the run's travel T, scaled to
    L (sigma^2 = sigma_rad^2 + (turn L / T)^2): in a bend the prior fades, on a straight
    run it stays about ``sigma_rad`` (plus the head's wobble, likewise scaled).
    """
    z = world_from_rig[:, :3, 2] / np.linalg.norm(world_from_rig[:, :3, 2], axis=1, keepdims=True)
    pos = world_from_rig[:, :3, 3]
    travel = float(np.linalg.norm(pos[-1] - pos[0]))
    turn = float(np.arccos(np.clip(z[0] @ z[-1], -1.0, 1.0)))
    lead = np.abs(np.einsum("ij,ij->i", centre - pos, z))
    rate = turn / travel if travel > 1e-6 else np.inf
    with np.errstate(invalid="ignore"):
        grow = np.where(lead > 0, rate * lead, 0.0)
    return AxisPrior(z, np.hypot(sigma_rad, grow))


def _ridge_direction(centres: np.ndarray, prior: np.ndarray, prior_sigma_rad: float) -> np.ndarray:
    """(3,) unit direction of the line through ``centres`` (M, 3) (mm) whose slope against
    the unit ``prior`` (3,) has a Gaussian prior N(0, ``prior_sigma_rad``^2): with e1, e2
    orthogonal to the prior and s the centres' coordinate along it, the slopes of
    x = c.e_j against s are sum(ds dx) / (sum(ds^2) + sigma_c^2 / sigma_p^2), sigma_c the
    centres' scatter about the unconstrained line (at least ``_CENTRE_NOISE_FLOOR_MM``)."""
    g = prior / np.linalg.norm(prior)
    if len(centres) < 2:
        return g
    e1, e2 = basis(g)
    c = centres - centres.mean(axis=0)
    ds = c @ g
    dx = np.column_stack([c @ e1, c @ e2])
    sss = float(ds @ ds)
    if sss < 1e-9:
        return g
    free = (ds @ dx) / sss
    scatter = dx - np.outer(ds, free)
    dof = max(2 * (len(c) - 2), 1)
    var_c = max(float(np.sum(scatter**2)) / dof, _CENTRE_NOISE_FLOOR_MM**2) if len(c) > 2 else 1e6
    slope = (ds @ dx) / (sss + var_c / prior_sigma_rad**2)
    d = g + slope[0] * e1 + slope[1] * e2
    return d / np.linalg.norm(d)

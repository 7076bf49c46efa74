"""The simulated pipe: centreline (straight / constant-radius bend), wall radius with defects
and the features of real pipes (joints, laterals, tapers, ovality, water: sim/features.py).

Pipe coordinates of a world point: arc length ``sigma`` (mm) along the centreline,
radial distance ``rho`` (mm) from it, and angle ``theta`` (rad) around it, measured
from the transported normal N towards the binormal B. At sigma = 0 the centreline
is at the world origin with tangent T = +z, N = +x and B = +y; the frame (N, B, T)
is parallel-transported through the bend, so a defect's angle means the same
thing anywhere along the pipe.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numba
import numpy as np

from omnipipe.errors import ConfigError
from omnipipe.sim.features import (
    PipeFeatures,
    WallTables,
    pack_tables,
    section_table_kernel,
    wall_radius_kernel,
    wall_radius_one,
)

DEFECT_KINDS = ("bulge", "dent")


@dataclass(frozen=True)
class Defect:
    """A local deviation of the wall (the contract's defect definition).

    The radial profile is ``height * p(sigma - centre; length, edge_length) *
    p(arc - centre; width, edge_width)`` with the raised-cosine plateau ``p`` of
    :func:`plateau`, so the half-height extents are exactly ``length`` and ``width``.

    Attributes:
        kind: "bulge" (into the pipe, radius smaller) or "dent" (out of it).
        height_mm: largest radial deviation (mm).
        width_mm: circumferential arc length at half height (mm).
        length_mm: axial extent at half height (mm).
        axial_start_mm: centreline arc length where the half-height extent starts (mm).
        angle_deg: angle of the defect's centre around the axis (deg, N towards B).
        edge_width_mm, edge_length_mm: widths of the cosine ramps; None picks
            width and min(length, 2 width): a rounded strip.
    """

    kind: str
    height_mm: float
    width_mm: float
    length_mm: float
    axial_start_mm: float
    angle_deg: float
    edge_width_mm: float | None = None
    edge_length_mm: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in DEFECT_KINDS:
            raise ConfigError("defect.kind", f"must be bulge or dent, got {self.kind!r}")
        for name in ("height_mm", "width_mm", "length_mm"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"defect.{name}", f"must be > 0, got {getattr(self, name)}")

    @property
    def ramp_width_mm(self) -> float:
        return (
            self.width_mm if self.edge_width_mm is None else min(self.edge_width_mm, self.width_mm)
        )

    @property
    def ramp_length_mm(self) -> float:
        if self.edge_length_mm is not None:
            return min(self.edge_length_mm, self.length_mm)
        return min(self.length_mm, 2.0 * self.width_mm)

    @property
    def sign(self) -> float:
        """+1 for a dent (radius grows), -1 for a bulge."""
        return 1.0 if self.kind == "dent" else -1.0

    @property
    def axial_centre_mm(self) -> float:
        return self.axial_start_mm + 0.5 * self.length_mm


def plateau(x: np.ndarray, full_width: float, ramp: float) -> np.ndarray:
    """Raised-cosine plateau: 1 inside, 0 outside, 0.5 exactly at |x| = full_width / 2."""
    ax = np.abs(x)
    inner = 0.5 * (full_width - ramp)
    phase = np.clip((ax - inner) / ramp, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * phase))


@dataclass(frozen=True)
class Centreline:
    """Straight, then an optional constant-radius bend, then straight (mm, deg).

    Attributes:
        straight_mm: length of the first straight section (sigma from 0).
        bend_radius_mm: radius of the bend's centreline arc; None for a straight pipe.
        bend_angle_deg: angle turned by the bend.
        bend_direction_deg: direction the bend turns to, around the axis from +x to +y.
    """

    straight_mm: float = 1.0e4
    bend_radius_mm: float | None = None
    bend_angle_deg: float = 0.0
    bend_direction_deg: float = 0.0

    @property
    def has_bend(self) -> bool:
        return self.bend_radius_mm is not None and self.bend_angle_deg > 0


@dataclass
class Pipe:
    """The true pipe of a simulated scene.

    Attributes:
        inner_diameter_mm: nominal inner diameter (mm).
        centreline: the axis geometry.
        defects: bulges and dents.
        ovality: (Dmax - Dmin) / D of an elliptic cross-section, 0 for round.
        ovality_angle_deg: direction of the major axis around the pipe axis.
        features: joints, laterals, tapers, local ovality, standing water, gravity.
            The wall function is fixed at construction: build a new Pipe to change
            defects or features.
    """

    inner_diameter_mm: float
    centreline: Centreline = field(default_factory=Centreline)
    defects: list[Defect] = field(default_factory=list)
    ovality: float = 0.0
    ovality_angle_deg: float = 0.0
    features: PipeFeatures = field(default_factory=PipeFeatures)

    def __post_init__(self) -> None:
        if not self.inner_diameter_mm > 0:
            raise ConfigError(
                "pipe.inner_diameter_mm", f"must be > 0, got {self.inner_diameter_mm}"
            )
        cl = self.centreline
        if cl.has_bend and cl.bend_radius_mm <= self.radius_mm:  # type: ignore[operator]
            raise ConfigError("pipe.centreline.bend_radius_mm", "must exceed the pipe radius")
        t0 = np.array([0.0, 0.0, 1.0])
        phi = math.radians(cl.bend_direction_deg)
        self._u_b = np.array([math.cos(phi), math.sin(phi), 0.0])  # bend direction at sigma=0
        self._w = np.cross(t0, self._u_b)  # bend-plane normal, constant
        self._phi = phi
        self._t0 = t0
        self._p1 = cl.straight_mm * t0
        if cl.has_bend:
            self._rb = float(cl.bend_radius_mm)  # type: ignore[arg-type]
            self._big_phi = math.radians(cl.bend_angle_deg)
            self._cb = self._p1 + self._rb * self._u_b
            self._sigma2 = cl.straight_mm + self._rb * self._big_phi
        else:
            self._rb = math.inf
            self._big_phi = 0.0
            self._sigma2 = math.inf
        self._tables: WallTables | None = None
        if self.features.shapes_wall:
            self._tables = pack_tables(
                self.radius_mm,
                self.ovality,
                self.ovality_angle_deg,
                self.features,
                _defect_table(self.defects),
            )
        self._check_features()

    @property
    def radius_mm(self) -> float:
        return 0.5 * self.inner_diameter_mm

    # -- centreline -----------------------------------------------------------------
    def frame_at(self, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Centreline point and transported frame at arc lengths ``sigma``.

        Returns:
            points, N, B, T: each (M, 3), world frame (mm / unit vectors).
        """
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        cl = self.centreline
        pts = s[:, None] * self._t0
        tang = np.empty((len(s), 3))
        tang[:] = self._t0
        nb_u = np.empty((len(s), 3))  # transported bend direction
        nb_u[:] = self._u_b
        if cl.has_bend:
            idx = np.flatnonzero(s > cl.straight_mm)
            if len(idx):
                alpha = np.minimum((s[idx] - cl.straight_mm) / self._rb, self._big_phi)
                ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
                arc_t = self._u_b * sa + self._t0 * ca
                after = np.maximum(s[idx] - self._sigma2, 0.0)[:, None]
                pts[idx] = (
                    self._cb - self._rb * self._u_b * ca + self._rb * self._t0 * sa + after * arc_t
                )
                tang[idx] = arc_t
                nb_u[idx] = self._u_b * ca - self._t0 * sa
        cp, sp = math.cos(self._phi), math.sin(self._phi)
        normal = cp * nb_u - sp * self._w
        binormal = sp * nb_u + cp * self._w
        return pts, normal, binormal, tang

    def pipe_coordinates(self, points_in_world: np.ndarray) -> tuple[np.ndarray, ...]:
        """Pipe coordinates of (M, 3) world points.

        Returns:
            sigma, rho, theta: (M,) arc length (mm), radial distance (mm), angle (rad).
            radial: (M, 3) unit vectors from the centreline to the points.
            tangent, normal, binormal: (M, 3) the transported frame at sigma.
        """
        X = np.ascontiguousarray(points_in_world, dtype=float).reshape(-1, 3)
        cl = self.centreline
        if cl.has_bend:
            end_pt, _, _, end_t = self.frame_at(np.array([self._sigma2]))
            bend = np.array([self._rb, self._big_phi, cl.straight_mm, self._sigma2, self._phi])
            return _pipe_coordinates_bent(
                X, self._t0, self._u_b, self._w, self._cb, end_pt[0], end_t[0], bend
            )
        sigma = X @ self._t0
        centre, normal, binormal, tangent = self.frame_at(sigma)
        e = X - centre
        rho = np.sqrt(np.einsum("ij,ij->i", e, e))
        radial = e / np.maximum(rho, 1e-12)[:, None]
        theta = np.arctan2(np.einsum("ij,ij->i", e, binormal), np.einsum("ij,ij->i", e, normal))
        return sigma, rho, theta, radial, tangent, normal, binormal

    def ray_distance_to_radius(
        self,
        origin_in_world: np.ndarray,
        rays_in_world: np.ndarray,
        radius: float,
        start: np.ndarray,
    ) -> np.ndarray:
        """Distances along unit rays where the distance to the centreline is ``radius`` (mm).

        Newton from ``start`` (M,), per ray; exact for straight pipes after one step.
        """
        o = np.asarray(origin_in_world, dtype=float)
        D = np.ascontiguousarray(rays_in_world, dtype=float)
        t = np.array(start, dtype=float)
        if not self.centreline.has_bend:
            return t
        cl = self.centreline
        end_pt, _, _, end_t = self.frame_at(np.array([self._sigma2]))
        bend = np.array([self._rb, self._big_phi, cl.straight_mm, self._sigma2, self._phi])
        return _ray_radius_bent(
            o, D, t, float(radius), self._t0, self._u_b, self._cb, end_pt[0], end_t[0], bend
        )

    def sigma_theta(self, points_in_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sigma, theta) of (M, 3) world points; cheap for straight pipes."""
        if not self.centreline.has_bend:
            X = np.asarray(points_in_world, dtype=float)
            sigma = X[:, 2] if self.centreline.straight_mm > 0 else X @ self._t0
            return sigma, np.arctan2(X[:, 1], X[:, 0])
        sigma, _, theta, *_ = self.pipe_coordinates(points_in_world)
        return sigma, theta

    # -- wall -------------------------------------------------------------------------
    def wall_radius(self, sigma: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """True wall radius (mm) at (sigma, theta): nominal, ovality, features and defects."""
        sigma = np.asarray(sigma, dtype=float)
        theta = np.asarray(theta, dtype=float)
        if self._tables is not None:
            s, th = np.broadcast_arrays(sigma, theta)
            tb = self._tables
            flat = wall_radius_kernel(
                np.ascontiguousarray(s, dtype=float).ravel(),
                np.ascontiguousarray(th, dtype=float).ravel(),
                tb.base,
                tb.tapers,
                tb.ovals,
                tb.joints,
                tb.offsets,
                tb.defects,
            )
            return flat.reshape(s.shape)
        radius = np.full(np.broadcast(sigma, theta).shape, self.radius_mm)
        if self.ovality:
            # r(theta) = R (1 + (ov/2) cos 2(theta - theta0)): (Dmax - Dmin)/D = ov.
            radius = radius * (
                1.0
                + 0.5 * self.ovality * np.cos(2.0 * (theta - math.radians(self.ovality_angle_deg)))
            )
        for dft in self.defects:
            radius = radius + self.defect_deviation(dft, sigma, theta)
        return radius

    def defect_deviation(self, dft: Defect, sigma: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Signed radial deviation (mm, + outwards) of one defect at (sigma, theta)."""
        dtheta = np.mod(theta - math.radians(dft.angle_deg) + np.pi, 2 * np.pi) - np.pi
        arc = dtheta * self.radius_mm
        axial = plateau(sigma - dft.axial_centre_mm, dft.length_mm, dft.ramp_length_mm)
        circ = plateau(arc, dft.width_mm, dft.ramp_width_mm)
        return dft.sign * dft.height_mm * axial * circ

    def max_deviation(self) -> tuple[float, float]:
        """(largest inward, largest outward) deviation from the nominal radius (mm, >= 0)."""
        inward = sum(d.height_mm for d in self.defects if d.kind == "bulge")
        outward = sum(d.height_mm for d in self.defects if d.kind == "dent")
        ov = 0.5 * self.ovality * self.radius_mm
        return inward + ov, outward + ov

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (scene.json's ``pipe``; ``features`` only when present)."""
        out = {
            "inner_diameter_mm": self.inner_diameter_mm,
            "ovality": self.ovality,
            "ovality_angle_deg": self.ovality_angle_deg,
            "centreline": asdict(self.centreline),
            "defects": [asdict(d) for d in self.defects],
        }
        if not self.features.empty:
            out["features"] = self.features.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Pipe:
        """Inverse of :meth:`to_dict`."""
        return cls(
            inner_diameter_mm=float(data["inner_diameter_mm"]),
            centreline=Centreline(**data.get("centreline", {})),
            defects=[Defect(**d) for d in data.get("defects", [])],
            ovality=float(data.get("ovality", 0.0)),
            ovality_angle_deg=float(data.get("ovality_angle_deg", 0.0)),
            features=PipeFeatures.from_dict(data.get("features", {})),
        )

    # -- features -----------------------------------------------------------------------
    def _check_features(self) -> None:
        for k, lat in enumerate(self.features.laterals):
            d_main = 2.0 * self.nominal_radius(np.array([lat.axial_mm]))[0]
            if lat.diameter_mm > 0.8 * d_main:
                raise ConfigError(
                    f"features.laterals[{k}].diameter_mm",
                    f"must be at most 0.8 x the main diameter ({0.8 * d_main:.1f} mm)",
                )
        if self.features.water is not None:
            ref = np.array([self.features.water.reference_mm])
            if not self.features.water.depth_mm < 2.0 * self.nominal_radius(ref)[0]:
                raise ConfigError("features.water.depth_mm", "must be less than the diameter")

    def nominal_radius(self, sigma: np.ndarray) -> np.ndarray:
        """(M,) radius (mm) of the round section at ``sigma``: the nominal one changed by tapers."""
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        r = np.full(s.shape, self.radius_mm)
        before = self.radius_mm
        for t in sorted(self.features.tapers, key=lambda t: t.axial_from_mm):
            f = np.clip((s - t.axial_from_mm) / (t.axial_to_mm - t.axial_from_mm), 0.0, 1.0)
            r = r + (0.5 * t.diameter_to_mm - before) * f
            before = 0.5 * t.diameter_to_mm
        return r

    def wall_bounds(self) -> tuple[float, float]:
        """(smallest, largest) wall radius anywhere (mm): brackets for the ray casting."""
        inward, outward = (
            sum(d.height_mm for d in self.defects if d.kind == kind) for kind in ("bulge", "dent")
        )
        radii = [self.radius_mm] + [0.5 * t.diameter_to_mm for t in self.features.tapers]
        ov = self.ovality + sum(o.percent / 100.0 for o in self.features.ovalities)
        shift = 0.0
        if self._tables is not None and len(self._tables.offsets):
            shift = float(np.hypot(self._tables.offsets[:, 1], self._tables.offsets[:, 2]).max())
        depth = max((j.depth_mm for j in self.features.joints), default=0.0)
        lo = min(radii) * (1.0 - 0.5 * ov) - shift - inward
        hi = max(radii) * (1.0 + 0.5 * ov) + shift + depth + outward
        return lo, hi

    def breakpoints(self) -> np.ndarray:
        """Arc lengths (mm) where the wall function bends sharply: joint edges, taper ends.

        The renderer samples each ray's wall residual on the planes normal to the
        centreline there, so no narrow gap edge is stepped over."""
        out: list[float] = []
        for j in self.features.joints:
            # Five points across each edge (a ray can clip an edge's corner between two)
            # and the centre, where an offset section starts.
            out.append(j.axial_mm)
            for f in np.linspace(-0.5, 0.5, 5):
                a = 0.5 * j.gap_mm + f * j.edge_mm
                out += [j.axial_mm - a, j.axial_mm + a]
        for t in self.features.tapers:
            out += [t.axial_from_mm, t.axial_to_mm]
        return np.array(sorted(out), float)

    def section_table(self, sigma: np.ndarray, n_angles: int = 360) -> np.ndarray:
        """(M, 3) true Dmax, Dmin (mm) and the direction of Dmax (rad, N towards B, in [0, pi))
        of the cross-sections at ``sigma``: taper and ovality, not gaps or defects."""
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        tb = self._section_tables()
        return section_table_kernel(s, n_angles, tb.base, tb.tapers, tb.ovals)

    def up(self) -> np.ndarray:
        """(3,) unit vector against gravity, world frame."""
        return -np.asarray(self.features.gravity, float)

    def centreline_table(self) -> np.ndarray:
        """(24,) the centreline packed for the compiled kernels (see ``_coords_one``)."""
        out = np.zeros(24)
        out[0:3], out[3:6], out[6:9] = self._t0, self._u_b, self._w
        if self.centreline.has_bend:
            end_pt, _, _, end_t = self.frame_at(np.array([self._sigma2]))
            out[9:12], out[12:15], out[15:18] = self._cb, end_pt[0], end_t[0]
            out[18:23] = (
                self._rb,
                self._big_phi,
                self.centreline.straight_mm,
                self._sigma2,
                self._phi,
            )
            out[23] = 1.0
        return out

    def first_wall_crossing(
        self,
        origin_in_world: np.ndarray,
        rays_in_world: np.ndarray,
        t_in: np.ndarray,
        t_out: np.ndarray,
        n_samples: int = 20,
    ) -> np.ndarray:
        """(M,) distance (mm) where each unit ray first passes from inside the wall to outside.

        The wall residual (rho - wall radius) is sampled ``n_samples`` times evenly over
        [t_in, t_out] (t_in inside the wall) and on every plane of :meth:`breakpoints`
        the ray crosses there; the first sign change is refined by Illinois regula falsi.
        Needs a pipe with joints, tapers or local ovality.
        """
        tb = self._tables
        if tb is None:
            raise ConfigError("pipe.features", "first_wall_crossing needs a shaped wall")
        breaks = self.breakpoints()
        centre, _, _, tangent = self.frame_at(breaks) if len(breaks) else (np.zeros((0, 3)),) * 4
        return _first_crossing_kernel(
            np.asarray(origin_in_world, float),
            np.ascontiguousarray(rays_in_world, dtype=float),
            np.ascontiguousarray(t_in, dtype=float),
            np.ascontiguousarray(t_out, dtype=float),
            int(n_samples),
            np.ascontiguousarray(centre, dtype=float),
            np.ascontiguousarray(tangent, dtype=float),
            self.centreline_table(),
            tb.base,
            tb.tapers,
            tb.ovals,
            tb.joints,
            tb.offsets,
            tb.defects,
        )

    def _section_tables(self) -> WallTables:
        """The wall tables without gaps and defects (sections, tapers, ovality, offsets)."""
        tb = pack_tables(
            self.radius_mm, self.ovality, self.ovality_angle_deg, self.features, np.zeros((0, 7))
        )
        return WallTables(tb.base, tb.tapers, tb.ovals, np.zeros((0, 4)), tb.offsets, tb.defects)

    def invert_height(self, sigma: np.ndarray, n_angles: int = 720) -> np.ndarray:
        """(M,) height (mm, along :meth:`up`) of the lowest wall point of each section at
        ``sigma``: taper, ovality and joint offsets included, gaps and defects not."""
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        centre, normal, binormal, _ = self.frame_at(s)
        up = self.up()
        tb = self._section_tables()
        th = np.linspace(0.0, 2 * np.pi, n_angles, endpoint=False)
        out = np.empty(len(s))
        for i in range(len(s)):
            r = wall_radius_kernel(
                np.full(n_angles, s[i]),
                th,
                tb.base,
                tb.tapers,
                tb.ovals,
                tb.joints,
                tb.offsets,
                tb.defects,
            )
            dirs = np.cos(th)[:, None] * normal[i] + np.sin(th)[:, None] * binormal[i]
            out[i] = float(np.min((centre[i] + r[:, None] * dirs) @ up))
        return out

    def water_level(self) -> float | None:
        """Height (mm, along :meth:`up`) of the standing water's surface; None without water."""
        water = self.features.water
        if water is None:
            return None
        return float(self.invert_height(np.array([water.reference_mm]))[0]) + water.depth_mm

    def lateral_frame(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """World geometry of lateral ``index``.

        Returns:
            origin: (3,) where the branch axis leaves the main centreline (mm).
            axis: (3,) unit branch axis, away from the main pipe.
            ref: (3,) unit vector normal to the axis: angle 0 of the branch's texture.
            radius: branch radius (mm).
            end: axial coordinate (mm from origin) where the branch ends.
        """
        lat = self.features.laterals[index]
        beta = math.radians(lat.branch_angle_deg)
        c, n, b, t = self.frame_at(np.array([lat.axial_mm]))
        th = math.radians(lat.angle_deg)
        e = math.cos(th) * n[0] + math.sin(th) * b[0]
        r_main = float(self.nominal_radius(np.array([lat.axial_mm]))[0])
        origin = c[0] - r_main / math.tan(beta) * t[0]
        axis = math.cos(beta) * t[0] + math.sin(beta) * e
        ref = t[0] - (t[0] @ axis) * axis
        ref /= np.linalg.norm(ref)
        return origin, axis, ref, 0.5 * lat.diameter_mm, r_main / math.sin(beta) + lat.length_mm


def _defect_table(defects: list[Defect]) -> np.ndarray:
    """(K, 7) defects for the compiled wall kernel (features.WallTables.defects)."""
    return np.array(
        [
            (
                d.sign * d.height_mm,
                d.axial_centre_mm,
                d.length_mm,
                d.ramp_length_mm,
                math.radians(d.angle_deg),
                d.width_mm,
                d.ramp_width_mm,
            )
            for d in defects
        ],
        float,
    ).reshape(-1, 7)


@numba.njit(cache=True)
def _pipe_coordinates_bent(X, t0, u_b, w, cb, end_pt, end_t, bend):  # pragma: no cover - compiled
    """Pipe coordinates on a straight-bend-straight centreline (see Pipe.pipe_coordinates)."""
    rb, big_phi, straight, sigma2, phi = bend[0], bend[1], bend[2], bend[3], bend[4]
    cp, sp = math.cos(phi), math.sin(phi)
    m = X.shape[0]
    sigma = np.empty(m)
    rho = np.empty(m)
    theta = np.empty(m)
    radial = np.empty((m, 3))
    tangent = np.empty((m, 3))
    normal = np.empty((m, 3))
    binormal = np.empty((m, 3))
    for i in range(m):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        y0, y1, y2 = x0 - cb[0], x1 - cb[1], x2 - cb[2]
        alpha = math.atan2(
            y0 * t0[0] + y1 * t0[1] + y2 * t0[2], -(y0 * u_b[0] + y1 * u_b[1] + y2 * u_b[2])
        )
        if 0.0 < alpha <= big_phi:
            s = straight + rb * alpha
        elif alpha > big_phi:
            s = (
                sigma2
                + (x0 - end_pt[0]) * end_t[0]
                + (x1 - end_pt[1]) * end_t[1]
                + (x2 - end_pt[2]) * end_t[2]
            )
        else:
            s = min(x0 * t0[0] + x1 * t0[1] + x2 * t0[2], straight)
        if s > straight:
            a = min((s - straight) / rb, big_phi)
            ca, sa = math.cos(a), math.sin(a)
            after = max(s - sigma2, 0.0)
        else:
            ca, sa, after = 1.0, 0.0, 0.0
        # Centreline point c, tangent g and transported bend direction q (straight: a = 0).
        e0 = e1 = e2 = 0.0
        en = eb = 0.0
        for k in range(3):
            g = u_b[k] * sa + t0[k] * ca
            q = u_b[k] * ca - t0[k] * sa
            if s > straight:
                c = cb[k] - rb * u_b[k] * ca + rb * t0[k] * sa + after * g
            else:
                c = s * t0[k]
            ek = X[i, k] - c
            nk = cp * q - sp * w[k]
            bk = sp * q + cp * w[k]
            normal[i, k] = nk
            binormal[i, k] = bk
            tangent[i, k] = g
            radial[i, k] = ek
            en += ek * nk
            eb += ek * bk
            if k == 0:
                e0 = ek
            elif k == 1:
                e1 = ek
            else:
                e2 = ek
        r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        rr = max(r, 1e-12)
        for k in range(3):
            radial[i, k] /= rr
        sigma[i] = s
        rho[i] = r
        theta[i] = math.atan2(eb, en)
    return sigma, rho, theta, radial, tangent, normal, binormal


@numba.njit(cache=True)
def _rho_bent(x0, x1, x2, t0, u_b, cb, end_pt, end_t, bend):  # pragma: no cover - compiled
    """Distance of one point from the bent centreline and its unit radial vector."""
    rb, big_phi, straight, sigma2 = bend[0], bend[1], bend[2], bend[3]
    y0, y1, y2 = x0 - cb[0], x1 - cb[1], x2 - cb[2]
    alpha = math.atan2(
        y0 * t0[0] + y1 * t0[1] + y2 * t0[2], -(y0 * u_b[0] + y1 * u_b[1] + y2 * u_b[2])
    )
    if 0.0 < alpha <= big_phi:
        s = straight + rb * alpha
    elif alpha > big_phi:
        s = (
            sigma2
            + (x0 - end_pt[0]) * end_t[0]
            + (x1 - end_pt[1]) * end_t[1]
            + (x2 - end_pt[2]) * end_t[2]
        )
    else:
        s = min(x0 * t0[0] + x1 * t0[1] + x2 * t0[2], straight)
    if s > straight:
        a = min((s - straight) / rb, big_phi)
        ca, sa = math.cos(a), math.sin(a)
        after = max(s - sigma2, 0.0)
        c0 = cb[0] - rb * u_b[0] * ca + rb * t0[0] * sa + after * (u_b[0] * sa + t0[0] * ca)
        c1 = cb[1] - rb * u_b[1] * ca + rb * t0[1] * sa + after * (u_b[1] * sa + t0[1] * ca)
        c2 = cb[2] - rb * u_b[2] * ca + rb * t0[2] * sa + after * (u_b[2] * sa + t0[2] * ca)
    else:
        c0, c1, c2 = s * t0[0], s * t0[1], s * t0[2]
    e0, e1, e2 = x0 - c0, x1 - c1, x2 - c2
    r = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    rr = max(r, 1e-12)
    return r, e0 / rr, e1 / rr, e2 / rr


@numba.njit(cache=True)
def _ray_radius_bent(
    o, D, t, radius, t0, u_b, cb, end_pt, end_t, bend
):  # pragma: no cover - compiled
    """Newton on rho(o + t D) = radius per ray, in place on t (d rho/dt = D . e_rho)."""
    for i in range(D.shape[0]):
        ti = t[i]
        for _ in range(30):
            r, q0, q1, q2 = _rho_bent(
                o[0] + ti * D[i, 0],
                o[1] + ti * D[i, 1],
                o[2] + ti * D[i, 2],
                t0,
                u_b,
                cb,
                end_pt,
                end_t,
                bend,
            )
            g = r - radius
            slope = max(D[i, 0] * q0 + D[i, 1] * q1 + D[i, 2] * q2, 0.05)
            ti = min(max(ti - g / slope, 0.0), 5000.0)
            if abs(g) < 1e-7:
                break
        t[i] = ti
    return t


@numba.njit(cache=True)
def _coords_one(x0, x1, x2, cl):  # pragma: no cover - compiled
    """(sigma, rho, theta) of one world point; ``cl`` from Pipe.centreline_table."""
    if cl[23] == 0.0:  # straight along +z with N = +x, B = +y
        return x2, math.sqrt(x0 * x0 + x1 * x1), math.atan2(x1, x0)
    rb, big_phi, straight, sigma2, phi = cl[18], cl[19], cl[20], cl[21], cl[22]
    y0, y1, y2 = x0 - cl[9], x1 - cl[10], x2 - cl[11]
    alpha = math.atan2(
        y0 * cl[0] + y1 * cl[1] + y2 * cl[2], -(y0 * cl[3] + y1 * cl[4] + y2 * cl[5])
    )
    if 0.0 < alpha <= big_phi:
        s = straight + rb * alpha
    elif alpha > big_phi:
        s = sigma2 + (x0 - cl[12]) * cl[15] + (x1 - cl[13]) * cl[16] + (x2 - cl[14]) * cl[17]
    else:
        s = min(x0 * cl[0] + x1 * cl[1] + x2 * cl[2], straight)
    if s > straight:
        a = min((s - straight) / rb, big_phi)
        ca, sa = math.cos(a), math.sin(a)
        after = max(s - sigma2, 0.0)
    else:
        ca, sa, after = 1.0, 0.0, 0.0
    cp, sp = math.cos(phi), math.sin(phi)
    rr = 0.0
    en = 0.0
    eb = 0.0
    for k in range(3):
        g = cl[3 + k] * sa + cl[k] * ca
        q = cl[3 + k] * ca - cl[k] * sa
        if s > straight:
            c = cl[9 + k] - rb * cl[3 + k] * ca + rb * cl[k] * sa + after * g
        else:
            c = s * cl[k]
        xk = x0 if k == 0 else (x1 if k == 1 else x2)
        ek = xk - c
        rr += ek * ek
        en += ek * (cp * q - sp * cl[6 + k])
        eb += ek * (sp * q + cp * cl[6 + k])
    return s, math.sqrt(rr), math.atan2(eb, en)


@numba.njit(cache=True)
def _residual_one(t, o, d, cl, base, tapers, ovals, joints, offsets, defects):  # pragma: no cover
    s, rho, th = _coords_one(o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2], cl)
    return rho - wall_radius_one(s, th, base, tapers, ovals, joints, offsets, defects)


@numba.njit(cache=True)
def _first_crossing_kernel(
    o,
    D,
    t_in,
    t_out,
    n_uniform,
    plane_c,
    plane_t,
    cl,
    base,
    tapers,
    ovals,
    joints,
    offsets,
    defects,
):  # pragma: no cover - compiled
    """Per ray: samples (uniform and on the planes), first inside-to-outside sign change,
    then Illinois regula falsi (see Pipe.first_wall_crossing)."""
    m = D.shape[0]
    n_planes = plane_c.shape[0]
    out = np.empty(m)
    ts = np.empty(n_uniform + n_planes)
    for i in range(m):
        d = D[i]
        a, b = t_in[i], t_out[i]
        for k in range(n_uniform):
            ts[k] = a + (b - a) * k / (n_uniform - 1)
        n = n_uniform
        for k in range(n_planes):
            rate = d[0] * plane_t[k, 0] + d[1] * plane_t[k, 1] + d[2] * plane_t[k, 2]
            if rate != 0.0:
                tk = (
                    (plane_c[k, 0] - o[0]) * plane_t[k, 0]
                    + (plane_c[k, 1] - o[1]) * plane_t[k, 1]
                    + (plane_c[k, 2] - o[2]) * plane_t[k, 2]
                ) / rate
                if a < tk < b:  # insert in order (the uniform samples are sorted)
                    j = n
                    while j > 0 and ts[j - 1] > tk:
                        ts[j] = ts[j - 1]
                        j -= 1
                    ts[j] = tk
                    n += 1
        samples = ts
        lo = samples[n - 2]
        hi = samples[n - 1]
        t_prev = samples[0]
        g_prev = _residual_one(t_prev, o, d, cl, base, tapers, ovals, joints, offsets, defects)
        g_lo = 0.0
        g_hi = 0.0
        found = False
        for k in range(1, n):
            tk = samples[k]
            gk = _residual_one(tk, o, d, cl, base, tapers, ovals, joints, offsets, defects)
            if g_prev < 0.0 and gk >= 0.0:
                lo, hi, g_lo, g_hi = t_prev, tk, g_prev, gk
                found = True
                break
            t_prev, g_prev = tk, gk
        if not found:
            g_lo = _residual_one(lo, o, d, cl, base, tapers, ovals, joints, offsets, defects)
            g_hi = _residual_one(hi, o, d, cl, base, tapers, ovals, joints, offsets, defects)
        mid = lo
        for _ in range(40):
            den = g_hi - g_lo
            mid = lo - g_lo * (hi - lo) / den if den > 0.0 else 0.5 * (lo + hi)
            gm = _residual_one(mid, o, d, cl, base, tapers, ovals, joints, offsets, defects)
            if abs(gm) < 1e-7 or hi - lo < 1e-7:
                break
            if gm < 0.0:
                lo, g_lo = mid, gm
                g_hi *= 0.5
            else:
                hi, g_hi = mid, gm
                g_lo *= 0.5
        out[i] = mid
    return out

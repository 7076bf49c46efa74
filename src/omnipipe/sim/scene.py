"""The simulated pipe: centreline (straight / constant-radius bend), wall radius with defects.

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

import numpy as np

from omnipipe.errors import ConfigError

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
    """

    inner_diameter_mm: float
    centreline: Centreline = field(default_factory=Centreline)
    defects: list[Defect] = field(default_factory=list)
    ovality: float = 0.0
    ovality_angle_deg: float = 0.0

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
        tang = np.repeat(self._t0[None], len(s), axis=0)
        nb_u = np.repeat(self._u_b[None], len(s), axis=0)  # transported bend direction
        if cl.has_bend:
            alpha = np.clip((s - cl.straight_mm) / self._rb, 0.0, self._big_phi)
            ca, sa = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
            arc_pts = self._cb - self._rb * self._u_b * ca + self._rb * self._t0 * sa
            arc_t = self._u_b * sa + self._t0 * ca
            arc_n = self._u_b * ca - self._t0 * sa
            after = np.maximum(s - self._sigma2, 0.0)[:, None]
            in_bend = (s > cl.straight_mm)[:, None]
            pts = np.where(in_bend, arc_pts + after * arc_t, pts)
            tang = np.where(in_bend, arc_t, tang)
            nb_u = np.where(in_bend, arc_n, nb_u)
        cp, sp = math.cos(self._phi), math.sin(self._phi)
        normal = cp * nb_u - sp * self._w
        binormal = sp * nb_u + cp * self._w
        return pts, normal, binormal, tang

    def pipe_coordinates(self, points_in_world: np.ndarray) -> tuple[np.ndarray, ...]:
        """(sigma, rho, theta, radial_unit, frame_T) of (M, 3) world points.

        Returns:
            sigma, rho, theta: (M,) arc length (mm), radial distance (mm), angle (rad).
            radial: (M, 3) unit vectors from the centreline to the points.
            tangent: (M, 3) centreline tangents at sigma.
            normal, binormal: (M, 3) the transported frame at sigma.
        """
        X = np.asarray(points_in_world, dtype=float)
        cl = self.centreline
        sigma = X @ self._t0
        if cl.has_bend:
            Y = X - self._cb
            p = -(Y @ self._u_b)
            q = Y @ self._t0
            alpha = np.arctan2(q, p)
            in_arc = (alpha > 0) & (alpha <= self._big_phi)
            end_pt, _, _, end_t = self.frame_at(np.array([self._sigma2]))
            after = alpha > self._big_phi
            sigma = np.where(in_arc, cl.straight_mm + self._rb * alpha, sigma)
            sigma = np.where(after, self._sigma2 + (X - end_pt[0]) @ end_t[0], sigma)
            sigma = np.where(~(in_arc | after), np.minimum(sigma, cl.straight_mm), sigma)
        centre, normal, binormal, tangent = self.frame_at(sigma)
        e = X - centre
        rho = np.linalg.norm(e, axis=1)
        radial = e / np.maximum(rho, 1e-12)[:, None]
        theta = np.arctan2(np.sum(e * binormal, axis=1), np.sum(e * normal, axis=1))
        return sigma, rho, theta, radial, tangent, normal, binormal

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
        """True wall radius (mm) at (sigma, theta): nominal, ovality and defects."""
        sigma = np.asarray(sigma, dtype=float)
        theta = np.asarray(theta, dtype=float)
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
        """JSON-ready description (scene.json's ``pipe``)."""
        return {
            "inner_diameter_mm": self.inner_diameter_mm,
            "ovality": self.ovality,
            "ovality_angle_deg": self.ovality_angle_deg,
            "centreline": asdict(self.centreline),
            "defects": [asdict(d) for d in self.defects],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Pipe:
        """Inverse of :meth:`to_dict`."""
        return cls(
            inner_diameter_mm=float(data["inner_diameter_mm"]),
            centreline=Centreline(**data.get("centreline", {})),
            defects=[Defect(**d) for d in data.get("defects", [])],
            ovality=float(data.get("ovality", 0.0)),
            ovality_angle_deg=float(data.get("ovality_angle_deg", 0.0)),
        )

"""Parts of a real pipe that are not defects: joints, laterals, tapers, ovality, standing water.

Positions use the pipe convention of :mod:`omnipipe.sim.scene`: ``axial`` is the
centreline arc length sigma (mm) from sigma = 0, angles (deg) go around the axis
from the transported normal N towards the binormal B. The writer converts them to
the contract's convention (axial from the first frame's station, angles from the
first rig frame's x axis) for scene.json.

The wall radius of a pipe with joints, tapers or ovality is one compiled function
(:func:`wall_radius_kernel`), used both by the renderer's ray casting and by the
ground truth, so the two can never disagree.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numba
import numpy as np

from omnipipe.errors import ConfigError


def _positive(name: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(name, f"must be > 0, got {value}")


@dataclass(frozen=True)
class Joint:
    """A circumferential joint: an open gap, and the next section displaced radially.

    The gap is a recess of ``depth_mm`` beyond the wall whose half-depth extent along
    the axis is exactly ``gap_mm`` (raised-cosine edges ``edge_mm`` wide). The section
    downstream of the gap's centre is displaced by ``offset_mm`` towards
    ``offset_angle_deg`` relative to the section upstream (offsets of successive joints
    add up); the step hides in the gap.

    Attributes:
        axial_mm: centre of the gap (centreline arc length, mm).
        gap_mm: axial width of the gap at half depth (mm).
        depth_mm: radial depth of the gap beyond the upstream wall (mm).
        offset_mm: radial displacement of the downstream section (mm, >= 0).
        offset_angle_deg: its direction around the axis (deg, N towards B).
    """

    axial_mm: float
    gap_mm: float
    depth_mm: float = 8.0
    offset_mm: float = 0.0
    offset_angle_deg: float = 0.0

    def __post_init__(self) -> None:
        _positive("joint.gap_mm", self.gap_mm)
        _positive("joint.depth_mm", self.depth_mm)
        if not self.offset_mm >= 0:
            raise ConfigError("joint.offset_mm", f"must be >= 0, got {self.offset_mm}")

    @property
    def edge_mm(self) -> float:
        """Width of the gap's raised-cosine edges (mm): sharp, but smooth enough for normals."""
        return min(0.5, 0.25 * self.gap_mm)


@dataclass(frozen=True)
class Lateral:
    """A round branch pipe entering the wall.

    The branch is a cylinder of ``diameter_mm`` whose axis leaves the main centreline
    at ``branch_angle_deg`` to the downstream direction and crosses the main wall at
    (``axial_mm``, ``angle_deg``): the centre of the hole. It ends ``length_mm``
    beyond the hole's centre (further rays see nothing: a dark far end).

    Attributes:
        axial_mm: where the branch axis crosses the wall (centreline arc length, mm).
        angle_deg: direction of the branch around the axis (deg, N towards B).
        diameter_mm: inner diameter of the branch (mm).
        branch_angle_deg: angle between the main pipe's downstream axis and the branch
            axis (deg, 20..160; 90: a square tee).
        length_mm: length of the branch beyond the hole's centre (mm).
    """

    axial_mm: float
    angle_deg: float
    diameter_mm: float
    branch_angle_deg: float = 90.0
    length_mm: float = 800.0

    def __post_init__(self) -> None:
        _positive("lateral.diameter_mm", self.diameter_mm)
        _positive("lateral.length_mm", self.length_mm)
        if not 20.0 <= self.branch_angle_deg <= 160.0:
            raise ConfigError(
                "lateral.branch_angle_deg", f"must be in [20, 160], got {self.branch_angle_deg}"
            )


@dataclass(frozen=True)
class Taper:
    """A reducer (or increaser): the diameter changes linearly over [from, to].

    Attributes:
        axial_from_mm, axial_to_mm: start and end of the change (mm).
        diameter_to_mm: inner diameter after it (mm); before it, the diameter the pipe
            had there (the nominal one, or the previous taper's ``diameter_to_mm``).
    """

    axial_from_mm: float
    axial_to_mm: float
    diameter_to_mm: float

    def __post_init__(self) -> None:
        _positive("taper.diameter_to_mm", self.diameter_to_mm)
        if not self.axial_to_mm > self.axial_from_mm:
            raise ConfigError("taper.axial_to_mm", "must exceed taper.axial_from_mm")


@dataclass(frozen=True)
class Ovality:
    """An elliptic stretch: r = R (1 + (p/200) w(sigma) cos 2(theta - angle)).

    ``w`` is the raised-cosine plateau of the defects: 1 inside, 0.5 exactly at
    ``axial_from_mm`` and ``axial_to_mm``, blended over ``blend_mm`` around each.
    (Dmax - Dmin) / Dnominal = p / 100 where w = 1; the mean diameter stays nominal.

    Attributes:
        axial_from_mm, axial_to_mm: half-level extent (mm).
        percent: ovality (Dmax - Dmin) / Dnominal x 100.
        angle_deg: direction of the major axis (deg, N towards B).
        blend_mm: width of the blend at either end (mm).
    """

    axial_from_mm: float
    axial_to_mm: float
    percent: float
    angle_deg: float = 0.0
    blend_mm: float = 40.0

    def __post_init__(self) -> None:
        if not 0 < self.percent < 50:
            raise ConfigError("ovality.percent", f"must be in (0, 50), got {self.percent}")
        _positive("ovality.blend_mm", self.blend_mm)
        if not self.axial_to_mm - self.axial_from_mm >= self.blend_mm:
            raise ConfigError("ovality.axial_to_mm", "the stretch must be at least blend_mm long")


@dataclass(frozen=True)
class Water:
    """Standing water: a flat, level surface ``depth_mm`` above the invert at ``reference_mm``.

    The surface is the plane normal to gravity through that height; where the invert
    rises or falls (a taper, an offset joint) the depth changes with it. It is present
    for centreline arc lengths in [axial_from_mm, axial_to_mm].
    """

    depth_mm: float
    axial_from_mm: float = -1.0e5
    axial_to_mm: float = 1.0e5
    reference_mm: float = 0.0

    def __post_init__(self) -> None:
        _positive("water.depth_mm", self.depth_mm)
        if not self.axial_to_mm > self.axial_from_mm:
            raise ConfigError("water.axial_to_mm", "must exceed water.axial_from_mm")


@dataclass(frozen=True)
class PipeFeatures:
    """Everything of a real pipe beyond the ideal cylinder and its defects.

    Attributes:
        joints, laterals, tapers, ovalities: the features (pipe convention).
        water: standing water, or None.
        gravity: unit gravity direction in the world frame (world -y unless the scene
            says otherwise; at sigma = 0 the pipe's B axis is world +y, "up").
    """

    joints: tuple[Joint, ...] = ()
    laterals: tuple[Lateral, ...] = ()
    tapers: tuple[Taper, ...] = ()
    ovalities: tuple[Ovality, ...] = ()
    water: Water | None = None
    gravity: tuple[float, float, float] = (0.0, -1.0, 0.0)

    def __post_init__(self) -> None:
        g = np.asarray(self.gravity, float)
        if g.shape != (3,) or not abs(float(np.linalg.norm(g)) - 1.0) < 1e-6:
            raise ConfigError("features.gravity", f"must be a unit 3-vector, got {self.gravity}")
        ends = [(t.axial_from_mm, t.axial_to_mm) for t in sorted(self.tapers, key=_taper_key)]
        for (_, end), (start, _) in itertools.pairwise(ends):
            if start < end:
                raise ConfigError("features.tapers", "tapers must not overlap")

    @property
    def shapes_wall(self) -> bool:
        """True if the wall radius differs from the plain pipe's (joints, tapers, ovality)."""
        return bool(self.joints or self.tapers or self.ovalities)

    @property
    def empty(self) -> bool:
        return not (self.shapes_wall or self.laterals or self.water is not None)

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return {
            "joints": [asdict(j) for j in self.joints],
            "laterals": [asdict(v) for v in self.laterals],
            "tapers": [asdict(t) for t in self.tapers],
            "ovalities": [asdict(o) for o in self.ovalities],
            "water": None if self.water is None else asdict(self.water),
            "gravity": list(self.gravity),
        }

    @classmethod
    def from_dict(cls, data: dict) -> PipeFeatures:
        water = data.get("water")
        return cls(
            joints=tuple(Joint(**j) for j in data.get("joints", [])),
            laterals=tuple(Lateral(**v) for v in data.get("laterals", [])),
            tapers=tuple(Taper(**t) for t in data.get("tapers", [])),
            ovalities=tuple(Ovality(**o) for o in data.get("ovalities", [])),
            water=None if water is None else Water(**water),
            gravity=tuple(float(v) for v in data.get("gravity", (0.0, -1.0, 0.0))),  # type: ignore[arg-type]
        )


def _taper_key(t: Taper) -> float:
    return t.axial_from_mm


@dataclass(frozen=True)
class WallTables:
    """The wall function's parameters packed for the compiled kernel (float64 arrays).

    Attributes:
        base: (4,) nominal radius, global ovality (fraction), its angle (rad), nominal
            radius for defect arcs.
        tapers: (K, 3) from, to, radius change (mm).
        ovals: (K, 5) centre, length, blend (mm), ovality (fraction), angle (rad).
        joints: (K, 4) centre, gap, edge, depth (mm).
        offsets: (K, 3) joint centre (sorted), cumulative section offset along N, B (mm).
        defects: (K, 7) signed height, axial centre, length, ramp length, angle (rad),
            width, ramp width (mm).
    """

    base: np.ndarray
    tapers: np.ndarray
    ovals: np.ndarray
    joints: np.ndarray
    offsets: np.ndarray
    defects: np.ndarray


def pack_tables(
    radius_mm: float,
    ovality: float,
    ovality_angle_deg: float,
    features: PipeFeatures,
    defects: np.ndarray,
) -> WallTables:
    """Pack a pipe's wall parameters for :func:`wall_radius_kernel`."""
    tapers = []
    r_before = radius_mm
    for t in sorted(features.tapers, key=_taper_key):
        tapers.append((t.axial_from_mm, t.axial_to_mm, 0.5 * t.diameter_to_mm - r_before))
        r_before = 0.5 * t.diameter_to_mm
    ovals = [
        (
            0.5 * (o.axial_from_mm + o.axial_to_mm),
            o.axial_to_mm - o.axial_from_mm,
            o.blend_mm,
            o.percent / 100.0,
            math.radians(o.angle_deg),
        )
        for o in features.ovalities
    ]
    joints = sorted(features.joints, key=lambda j: j.axial_mm)
    offsets = []
    ox = oy = 0.0
    for j in joints:
        a = math.radians(j.offset_angle_deg)
        ox += j.offset_mm * math.cos(a)
        oy += j.offset_mm * math.sin(a)
        offsets.append((j.axial_mm, ox, oy))
    return WallTables(
        base=np.array([radius_mm, ovality, math.radians(ovality_angle_deg), radius_mm]),
        tapers=np.array(tapers, float).reshape(-1, 3),
        ovals=np.array(ovals, float).reshape(-1, 5),
        joints=np.array(
            [(j.axial_mm, j.gap_mm, j.edge_mm, j.depth_mm) for j in joints], float
        ).reshape(-1, 4),
        offsets=np.array(offsets, float).reshape(-1, 3),
        defects=np.asarray(defects, float).reshape(-1, 7),
    )


@numba.njit(cache=True)
def _plateau1(x, full, ramp):  # pragma: no cover - compiled
    """Scalar raised-cosine plateau (see scene.plateau)."""
    inner = 0.5 * (full - ramp)
    phase = min(max((abs(x) - inner) / ramp, 0.0), 1.0)
    return 0.5 * (1.0 + math.cos(math.pi * phase))


@numba.njit(cache=True)
def section_radius(s, th, base, tapers, ovals):  # pragma: no cover - compiled
    """Radius (mm) of the round-or-elliptic section at (s, th) about its own centre."""
    r = base[0]
    for k in range(tapers.shape[0]):
        f = min(max((s - tapers[k, 0]) / (tapers[k, 1] - tapers[k, 0]), 0.0), 1.0)
        r += tapers[k, 2] * f
    scale = 1.0
    if base[1] != 0.0:
        scale *= 1.0 + 0.5 * base[1] * math.cos(2.0 * (th - base[2]))
    for k in range(ovals.shape[0]):
        w = _plateau1(s - ovals[k, 0], ovals[k, 1], ovals[k, 2])
        if w > 0.0:
            scale *= 1.0 + 0.5 * ovals[k, 3] * w * math.cos(2.0 * (th - ovals[k, 4]))
    return r * scale


@numba.njit(cache=True)
def section_offset(s, offsets):  # pragma: no cover - compiled
    """(N, B) components (mm) of the section centre's displacement at arc length s."""
    ox = 0.0
    oy = 0.0
    for k in range(offsets.shape[0]):
        if s > offsets[k, 0]:
            ox = offsets[k, 1]
            oy = offsets[k, 2]
    return ox, oy


@numba.njit(cache=True)
def wall_radius_one(s, th, base, tapers, ovals, joints, offsets, defects):  # pragma: no cover
    """Wall radius (mm) from the centreline at (s mm, th rad): section, offset, gaps, defects.

    An offset section is its own shape about the displaced centre, evaluated at the
    angle seen from the centreline (exact for round sections; for an oval one the error
    is of order offset x ovality).
    """
    r0 = section_radius(s, th, base, tapers, ovals)
    ox, oy = section_offset(s, offsets)
    if ox != 0.0 or oy != 0.0:
        p = ox * math.cos(th) + oy * math.sin(th)
        q2 = ox * ox + oy * oy - p * p
        r = p + math.sqrt(max(r0 * r0 - q2, 0.0))
    else:
        r = r0
    for k in range(joints.shape[0]):
        if abs(s - joints[k, 0]) < 0.5 * (joints[k, 1] + joints[k, 2]):
            r += joints[k, 3] * _plateau1(s - joints[k, 0], joints[k, 1], joints[k, 2])
    for k in range(defects.shape[0]):
        ax = _plateau1(s - defects[k, 1], defects[k, 2], defects[k, 3])
        if ax > 0.0:
            dth = (th - defects[k, 4] + math.pi) % (2.0 * math.pi) - math.pi
            r += defects[k, 0] * ax * _plateau1(dth * base[3], defects[k, 5], defects[k, 6])
    return r


@numba.njit(cache=True)
def wall_radius_kernel(s, th, base, tapers, ovals, joints, offsets, defects):  # pragma: no cover
    """:func:`wall_radius_one` over flat arrays ``s``, ``th`` (same length)."""
    out = np.empty(s.shape[0])
    for i in range(s.shape[0]):
        out[i] = wall_radius_one(s[i], th[i], base, tapers, ovals, joints, offsets, defects)
    return out


@numba.njit(cache=True)
def section_table_kernel(s, n_angles, base, tapers, ovals):  # pragma: no cover - compiled
    """Per arc length: (Dmax, Dmin, angle of Dmax in rad) of the section (no gaps, defects)."""
    out = np.empty((s.shape[0], 3))
    for i in range(s.shape[0]):
        dmax = -1.0
        dmin = 1e300
        amax = 0.0
        for k in range(n_angles):
            th = math.pi * k / n_angles
            d = section_radius(s[i], th, base, tapers, ovals) + section_radius(
                s[i], th + math.pi, base, tapers, ovals
            )
            if d > dmax:
                dmax = d
                amax = th
            dmin = min(dmin, d)
        out[i, 0] = dmax
        out[i, 1] = dmin
        out[i, 2] = amax
    return out

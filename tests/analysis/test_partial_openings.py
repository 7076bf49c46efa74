"""A lateral's opening seen in part (the branch wall shallow and sparse on one side) and a
dent 30 mm from a joint: seeded synthetic rings against truth."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis import AnalysisConfig, AnalysisInputs, run
from omnipipe.geometry import make_transform
from omnipipe.sim.features import Joint, PipeFeatures
from omnipipe.sim.scene import Defect, Pipe

HOLE = (250.0, 60.0, 90.0)  # centre axial mm, angle deg, diameter mm (a square tee)


def _rings(
    pipe: Pipe, seed: int, hole: tuple[float, float, float] | None = HOLE, slope: float = 0.3
) -> AnalysisInputs:
    """Rings every 4 mm (jittered) over 100-400 mm of ``pipe``, 360 samples each (noise
    0.1 mm). In the ``hole`` (centre axial mm, angle deg, diameter mm) the branch wall
    lies 40-100 mm beyond the main wall upstream of its centre; downstream (the obtuse
    side, where the branch wall leaves the main wall gently) at most ``slope`` x its
    axial distance from the rim, so each ring's chord is shallow (within the feature
    threshold) towards its ends, where every other sample is lost (depth < 3 mm)."""
    rng = np.random.default_rng(seed)
    sig = np.arange(100.0, 400.0, 4.0) + rng.uniform(-0.5, 0.5, 75)
    theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    R = 0.5 * pipe.inner_diameter_mm
    pts, frame, poses = [], [], []
    for k, s0 in enumerate(sig):
        s = np.full(theta.size, s0)
        centre, normal, binormal, _ = pipe.frame_at(s)
        r = pipe.wall_radius(s, theta) + rng.normal(0, 0.1, theta.size)
        keep = np.ones(theta.size, bool)
        if hole is not None:
            zc, ac, dia = hole
            u = ((theta - np.radians(ac) + np.pi) % (2 * np.pi) - np.pi) * R
            half = R * np.arcsin(0.5 * dia / R)
            q = (u / half) ** 2 + ((s - zc) / (0.5 * dia)) ** 2
            in_hole = q < 1.0
            # Downstream of the centre the branch wall leaves the rim at a slope of
            # ``slope``: its depth grows from 0 at the rim (the chords' ends shallow).
            rim_down = zc + 0.5 * dia * np.sqrt(np.clip(1.0 - (u / half) ** 2, 0.0, 1.0))
            depth = 40.0 + 60.0 * rng.random(theta.size)
            obtuse = in_hole & (s > zc)
            depth[obtuse] = np.minimum(depth[obtuse], slope * (rim_down[obtuse] - s[obtuse]))
            r[in_hole] += depth[in_hole]
            keep &= ~(in_hole & (depth < 3.0) & (np.arange(theta.size) % 2 == 1))
        p = centre + (r * np.cos(theta))[:, None] * normal + (r * np.sin(theta))[:, None] * binormal
        pts.append(p[keep])
        frame.append(np.full(int(keep.sum()), k))
        c0, n0, b0, t0 = (a[0] for a in pipe.frame_at(np.array([s0])))
        poses.append(make_transform(np.stack([n0, b0, t0], axis=1), c0 + 82 * t0))
    return AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses))


def test_partly_seen_opening_is_placed_by_its_whole_reach() -> None:
    """Downstream of a 90 mm hole's centre the branch wall rises from the rim at 0.3:
    the rings' chords there are cut at both ends (shallow, sparse samples), and the
    deep samples' chord profile puts the centre upstream. The opening grown over the
    disturbed rings: one lateral, axial within 3 mm, clock within 3 deg, diameter within
    3 sigma; no defect."""
    res = run(AnalysisConfig(), _rings(Pipe(300.0), seed=41))
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(laterals) == 1, res.features
    lat = laterals[0]
    assert abs(lat.axial_mm - HOLE[0]) < 3.0, lat
    assert abs((lat.angle_deg - HOLE[1] + 180) % 360 - 180) < 3.0, lat
    assert abs(lat.diameter_mm - HOLE[2]) < max(3.0 * lat.diameter_sigma_mm, 3.0), lat
    assert res.defects == [], res.defects


def test_dent_30_mm_from_a_joint_is_found_and_sized() -> None:
    """A 3 mm dent 20 x 20 mm starting 30 mm downstream of an 8 mm joint's gap (no
    hole): the joint is found, and the dent is still reported with its height, start
    and clock (as beside a plain wall)."""
    joint = Joint(200.0, 8.0, 10.0, 0.0, 0.0)
    dent = Defect("dent", 3.0, 20.0, 20.0, 234.0, 150.0)
    pipe = Pipe(300.0, defects=[dent], features=PipeFeatures(joints=(joint,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=47, hole=None))
    assert len([f for f in res.features if f.kind == "joint"]) == 1, res.features
    assert len(res.defects) == 1, res.defects
    d = res.defects[0]
    assert d.kind == "dent"
    assert abs(d.height_mm - 3.0) < 0.4
    assert abs(d.axial_start_mm - 234.0) < 3.0
    assert abs((d.angle_deg - 150.0 + 180) % 360 - 180) < 3.0

"""Joints and laterals: found, measured within tolerance, and never reported as defects."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omnipipe.analysis import AnalysisConfig, AnalysisInputs, run
from omnipipe.analysis.records import AnalysisResult
from omnipipe.geometry import make_transform
from omnipipe.sim.features import Joint, PipeFeatures, Taper
from omnipipe.sim.scene import Defect, Pipe

JOINT = Joint(200.0, 8.0, 10.0, 3.0, 90.0)
HOLE = (300.0, 120.0, 100.0)  # a square tee: centre axial mm, angle deg, diameter mm


def _rings(
    pipe: Pipe,
    seed: int,
    spacing: float = 4.0,
    tilt_deg: float = 0.0,
    hole: tuple[float, float, float] = HOLE,
    reach: tuple[float, float] = (40.0, 100.0),
    lost: float = 0.0,
    dry_band: tuple[float, float] | None = None,
    in_plane: bool = False,
) -> AnalysisInputs:
    """Rings every ``spacing`` mm (jittered) over 100-400 mm of ``pipe``, tilted by
    ``tilt_deg`` to the axis (as a robot leaning in the pipe: a ring's samples spread
    along the axis); points in the tee's ``hole`` (centre axial mm, angle deg, diameter
    mm) lie on the branch wall, ``reach`` (first + up to second) mm beyond the main wall,
    except the hole's middle ``lost`` (fraction of its semi-axes) where the light is lost
    in the branch (no sample); ``dry_band`` (from, to deg): no ring returns there (a
    shadow along the whole run); ``in_plane``: the branch wall's samples lie in the
    tilted ring's plane (their axial position moves with their reach, as the laser's
    light does), else abreast of the wall sample they replace."""
    rng = np.random.default_rng(seed)
    sig = np.arange(100.0, 400.0, spacing) + rng.uniform(-0.5, 0.5, int(np.ceil(300 / spacing)))
    theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    R = 0.5 * pipe.inner_diameter_mm
    zc, ac, dia = hole
    pts, frame, poses = [], [], []
    for k in range(len(sig)):
        s = sig[k] + R * np.tan(np.radians(tilt_deg)) * np.cos(theta - 0.7)
        centre, normal, binormal, _ = pipe.frame_at(s)
        r = pipe.wall_radius(s, theta) + rng.normal(0, 0.1, theta.size)
        u = ((theta - np.radians(ac) + np.pi) % (2 * np.pi) - np.pi) * R
        half = R * np.arcsin(0.5 * dia / R)  # the hole's chord is its diameter
        in_hole = (u / half) ** 2 + ((s - zc) / (0.5 * dia)) ** 2 < 1.0
        r[in_hole] += reach[0] + reach[1] * rng.random(in_hole.sum())
        if in_plane:
            s = sig[k] + r * np.tan(np.radians(tilt_deg)) * np.cos(theta - 0.7)
            centre, normal, binormal, _ = pipe.frame_at(s)
        keep = (u / half) ** 2 + ((s - zc) / (0.5 * dia)) ** 2 >= lost**2
        if dry_band is not None:
            keep &= ~((np.degrees(theta) % 360 >= dry_band[0]) & (np.degrees(theta) % 360 <= dry_band[1]))
        p = centre + (r * np.cos(theta))[:, None] * normal + (r * np.sin(theta))[:, None] * binormal
        pts.append(p[keep])
        frame.append(np.full(int(keep.sum()), k))
        c0, n0, b0, t0 = (a[0] for a in pipe.frame_at(np.array([sig[k]])))
        poses.append(make_transform(np.stack([n0, b0, t0], axis=1), c0 + 82 * t0))
    return AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses))


def _check_features(res: AnalysisResult, joint: Joint = JOINT) -> None:
    joints = [f for f in res.features if f.kind == "joint"]
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(joints) == 1 and len(laterals) == 1, res.features
    j, t = joints[0], joint
    assert abs(j.axial_mm - t.axial_mm) < 3.0
    assert abs(j.gap_mm - t.gap_mm) < max(3.0 * j.gap_sigma_mm, 1.0)
    assert abs(j.offset_mm - t.offset_mm) < max(3.0 * j.offset_sigma_mm, 0.5)
    if t.offset_mm > 0:
        assert abs((j.offset_angle_deg - t.offset_angle_deg + 180) % 360 - 180) < 10.0
    lat = laterals[0]
    assert abs(lat.axial_mm - HOLE[0]) < 3.0
    assert abs((lat.angle_deg - HOLE[1] + 180) % 360 - 180) < 3.0
    assert abs(lat.diameter_mm - HOLE[2]) < max(3.0 * lat.diameter_sigma_mm, 3.0)
    c = j.to_contract()
    assert {"gap_mm", "gap_sigma_mm", "offset_mm", "offset_angle_deg", "axial_sigma_mm"} <= set(c)


def test_joint_and_lateral_are_features_not_defects() -> None:
    pipe = Pipe(300.0, features=PipeFeatures(joints=(JOINT,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=3))
    _check_features(res)
    assert res.defects == []
    assert abs(res.inner_diameter_mm - 300.0) < 0.5
    # The gap's and the hole's points are marked, the plain wall is not.
    assert res.point_not_wall.sum() > 0
    assert res.point_not_wall.mean() < 0.15


@pytest.mark.parametrize("offset_mm", [0.0, 3.0])
def test_dent_beside_a_joint_is_still_found_and_sized(offset_mm: float) -> None:
    """Also beside an offset joint: the sections either side are fitted separately."""
    dent = Defect("dent", 3.0, 30.0, 20.0, 215.0, 270.0)
    joint = replace(JOINT, offset_mm=offset_mm)
    pipe = Pipe(300.0, defects=[dent], features=PipeFeatures(joints=(joint,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=5))
    _check_features(res, joint)
    assert len(res.defects) == 1, res.defects
    d = res.defects[0]
    assert d.kind == "dent"
    assert abs(d.height_mm - 3.0) < 0.4
    assert abs(d.axial_start_mm - 215.0) < 3.0
    assert abs(d.length_mm - 20.0) < 4.0
    assert abs((d.angle_deg - 270.0 + 180) % 360 - 180) < 3.0


def test_narrow_joint_between_tilted_rings_is_found() -> None:
    """A 5 mm gap between rings 8 mm apart: rings tilted 6 deg cross it along a slant,
    and together see it all round; gap, position and offset within 3 sigma."""
    joint = Joint(200.0, 5.0, 8.0, 2.0, 200.0)
    pipe = Pipe(300.0, features=PipeFeatures(joints=(joint,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=7, spacing=8.0, tilt_deg=6.0))
    joints = [f for f in res.features if f.kind == "joint"]
    assert len(joints) == 1, res.features
    j = joints[0]
    assert abs(j.axial_mm - 200.0) < max(3.0 * j.axial_sigma_mm, 1.0)
    assert abs(j.gap_mm - 5.0) < max(3.0 * j.gap_sigma_mm, 1.0)
    assert abs(j.offset_mm - 2.0) < max(3.0 * j.offset_sigma_mm, 0.3)
    assert abs((j.offset_angle_deg - 200.0 + 180) % 360 - 180) < 10.0
    assert res.defects == []


def test_joint_beside_a_lateral_on_sparse_rings_is_its_own_band() -> None:
    """Rings 20 mm apart (sewer-small): one ring in an 8 mm joint gap 20 mm before a
    100 mm tee's opening, linked to the opening's rings along the axis. The joint's band
    is its ring's, not the 120 mm from the joint through the opening: one joint (at the
    gap; its edges somewhere between the ring in it and the next rings, 20 mm out: the
    gap within 3 sigma and under two rings' spacing), one lateral, no defect."""
    joint = Joint(236.0, 8.0, 10.0, 0.0, 0.0)
    pipe = Pipe(300.0, features=PipeFeatures(joints=(joint,)))
    inputs = _rings(pipe, seed=5, spacing=20.0)
    res = run(AnalysisConfig(), inputs)
    joints = [f for f in res.features if f.kind == "joint"]
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(joints) == 1 and len(laterals) == 1, res.features
    j = joints[0]
    assert abs(j.axial_mm - joint.axial_mm) < 10.0, joints
    assert abs(j.gap_mm - joint.gap_mm) <= 3.0 * j.gap_sigma_mm and j.gap_mm < 40.0, joints
    assert res.defects == []


def test_joint_inside_a_taper_on_sparse_rings_is_found() -> None:
    """Rings 20 mm apart through a reducer (300 -> 250 mm over 140 mm): one ring lies in
    a 10 mm gap, 3 mm deep, and stands above both its neighbours though the running
    median of the rings' radii lags the taper. One joint, at the gap, its gap and
    position within 3 sigma; no false joint elsewhere in the taper; no defect."""
    joint = Joint(240.0, 10.0, 6.0, 0.0, 0.0)
    taper = Taper(180.0, 320.0, 250.0)
    pipe = Pipe(300.0, features=PipeFeatures(joints=(joint,), tapers=(taper,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=11, spacing=20.0))
    joints = [f for f in res.features if f.kind == "joint"]
    assert len(joints) == 1, res.features
    j = joints[0]
    assert abs(j.axial_mm - joint.axial_mm) < max(3.0 * j.axial_sigma_mm, 1.0)
    assert abs(j.gap_mm - joint.gap_mm) < max(3.0 * j.gap_sigma_mm, 1.0)
    assert res.defects == []


def test_offset_of_a_joint_one_ring_from_the_run_start_is_measured() -> None:
    """A 3 mm offset joint 10 mm into the run (rings 8 mm apart, one of them upstream of
    the gap): the offset is measured (within 3 sigma, direction within 15 deg), not
    left out."""
    joint = Joint(110.0, 5.0, 8.0, 3.0, 90.0)
    pipe = Pipe(300.0, features=PipeFeatures(joints=(joint,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=13, spacing=8.0))
    joints = [f for f in res.features if f.kind == "joint"]
    assert len(joints) == 1, res.features
    j = joints[0]
    assert abs(j.axial_mm - joint.axial_mm) < 3.0
    assert j.offset_mm is not None and j.offset_sigma_mm is not None
    assert abs(j.offset_mm - joint.offset_mm) < max(3.0 * j.offset_sigma_mm, 0.3)
    assert abs((j.offset_angle_deg - joint.offset_angle_deg + 180) % 360 - 180) < 15.0


def test_small_lateral_seen_a_little_way_in_is_a_feature_not_a_dent() -> None:
    """A 40 mm branch (0.1 D) in a 400 mm pipe whose wall is seen only 20-28 mm beyond
    the main wall (less than 0.08 D): a lateral at its place, no dent there."""
    pipe = Pipe(400.0)
    hole = (250.0, 60.0, 40.0)
    res = run(AnalysisConfig(), _rings(pipe, seed=17, spacing=4.0, hole=hole, reach=(20.0, 8.0)))
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(laterals) == 1, res.features
    lat = laterals[0]
    assert abs(lat.axial_mm - hole[0]) < 3.0
    assert abs((lat.angle_deg - hole[1] + 180) % 360 - 180) < 3.0
    assert abs(lat.diameter_mm - hole[2]) < max(3.0 * lat.diameter_sigma_mm, 3.0)
    assert res.defects == []
    assert not [f for f in res.features if f.kind == "joint"]


def test_narrow_deep_dent_stays_a_dent() -> None:
    """An 8 mm deep, 30 mm wide dent where the wall is clean (noise 0.1 mm, threshold
    1.5 mm): far beyond the small-opening threshold, but wider than deep: a dent, no
    lateral."""
    dent = Defect("dent", 8.0, 30.0, 20.0, 215.0, 270.0)
    pipe = Pipe(300.0, defects=[dent])
    res = run(AnalysisConfig(), _rings(pipe, seed=19, hole=(0.0, 0.0, 1.0)))
    assert not [f for f in res.features if f.kind == "lateral"], res.features
    assert len(res.defects) == 1 and res.defects[0].kind == "dent", res.defects


def test_offset_joint_between_rings_is_found_by_its_offset() -> None:
    """A 3 mm gap no ring samples (rings 8 mm apart) with a 5 mm offset: found by the
    step of the sections, its position and gap within the unsampled stretch (3 sigma),
    its offset within 3 sigma; a plain run of the same rings has no joint."""
    joint = Joint(200.0, 3.0, 8.0, 5.0, 45.0)
    pipe = Pipe(300.0, features=PipeFeatures(joints=(joint,)))
    res = run(AnalysisConfig(), _rings(pipe, seed=23, spacing=8.0))
    joints = [f for f in res.features if f.kind == "joint"]
    assert len(joints) == 1, res.features
    j = joints[0]
    assert abs(j.axial_mm - joint.axial_mm) < 3.0 * j.axial_sigma_mm
    assert abs(j.gap_mm - joint.gap_mm) < 3.0 * j.gap_sigma_mm
    assert abs(j.offset_mm - joint.offset_mm) < max(3.0 * j.offset_sigma_mm, 0.3)
    assert abs((j.offset_angle_deg - joint.offset_angle_deg + 180) % 360 - 180) < 10.0
    assert res.defects == []
    plain = run(AnalysisConfig(), _rings(Pipe(300.0), seed=23, spacing=8.0))
    assert not [f for f in plain.features if f.kind == "joint"], plain.features


@pytest.mark.parametrize("lost", [1.0, 0.6])
def test_lateral_seen_as_lost_returns_is_a_feature_not_a_dent(lost: float) -> None:
    """A 60 mm branch (0.2 D) whose light is lost in the branch: no sample at all in the
    hole (lost 1.0), or the branch wall lit only near the rim (lost 0.6). A lateral at
    its place (axial, clock within 3 mm / 3 deg, diameter within 3 sigma), no defect,
    no joint, no water."""
    pipe = Pipe(300.0)
    hole = (260.0, 75.0, 60.0)
    res = run(AnalysisConfig(), _rings(pipe, seed=29, hole=hole, reach=(15.0, 10.0), lost=lost))
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(laterals) == 1, res.features
    lat = laterals[0]
    assert abs(lat.axial_mm - hole[0]) < 3.0
    assert abs((lat.angle_deg - hole[1] + 180) % 360 - 180) < 3.0
    assert abs(lat.diameter_mm - hole[2]) < max(3.0 * lat.diameter_sigma_mm, 3.0)
    assert res.defects == []
    assert not [f for f in res.features if f.kind in ("joint", "water")], res.features


def test_returns_lost_along_the_whole_run_are_no_lateral() -> None:
    """No ring returns light between 250 and 280 deg over the whole run (a shadow, a
    dropout band): not an opening."""
    res = run(AnalysisConfig(), _rings(Pipe(300.0), seed=31, hole=(0.0, 0.0, 1.0), dry_band=(250.0, 280.0)))
    assert not [f for f in res.features if f.kind == "lateral"], res.features


def test_lateral_on_tilted_rings_is_placed_by_the_rings_not_the_branch_wall() -> None:
    """Rings tilted 6 deg to the axis: the branch wall lit through a 60 mm hole lies in
    each ring's plane, 40-140 mm beyond the main wall, so 4-15 mm further along the axis
    than the ring at the rim. The lateral is placed by the rings (axial within 3 mm and
    3 sigma, clock within 3 deg, diameter within 3 sigma), not by the branch wall."""
    pipe = Pipe(300.0)
    hole = (250.0, 40.0, 60.0)
    res = run(AnalysisConfig(), _rings(pipe, seed=37, tilt_deg=6.0, hole=hole, reach=(40.0, 100.0), in_plane=True))
    laterals = [f for f in res.features if f.kind == "lateral"]
    assert len(laterals) == 1, res.features
    lat = laterals[0]
    assert abs(lat.axial_mm - hole[0]) < min(3.0, 3.0 * lat.axial_sigma_mm), lat
    assert abs((lat.angle_deg - hole[1] + 180) % 360 - 180) < 3.0
    assert abs(lat.diameter_mm - hole[2]) < max(3.0 * lat.diameter_sigma_mm, 3.0)
    assert res.defects == []

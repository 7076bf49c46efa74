"""A wide joint gap seen at a slant: the fitted centreline tilted to the pipe (a short run
in a large, noisy pipe), the rings and the gap both slanted across the axial coordinate,
and several rings lying partly in the gap together (issue 30, bench seed 13)."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_rings import Rings
from omnipipe.analysis.feature_types import Joint, Lateral
from omnipipe.analysis.features import FeatureConfig, find_features
from omnipipe.analysis.joints import offset_joints

R = 267.0
GAP_AT, GAP_MM, DEPTH_MM = -190.0, 10.0, 11.5


def _line(arc: np.ndarray) -> Centreline:
    """A straight centreline along world z through the rings' stations."""
    return Centreline.straight(arc, R)


def _stacked(
    line: Centreline, theta: np.ndarray, rings: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each ring's (axial mm, radius mm) samples at the angles ``theta`` (rad), stacked
    as find_features takes them: ``line``, sigma, rho, theta, frame (the ring's index)."""
    sig = np.concatenate([a for a, _ in rings])
    rho = np.concatenate([b for _, b in rings])
    frame = np.repeat(np.arange(len(rings)), theta.size)
    return line, sig, rho, np.tile(theta, len(rings)), frame


def _scene(seed: int, gap: bool) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ten rings 3-8 mm apart over 50 mm, 540 samples each, wall noise 2 mm. Each ring
    strays +-12 mm along the axial coordinate (its plane tilted 2.6 deg to the fitted
    axis); the gap's plane +-8.4 mm (the pipe's true cross-section, 0.8 deg from the
    rings'), so the rings lying near it are partly in it."""
    rng = np.random.default_rng(seed)
    centres = GAP_AT + np.cumsum(np.r_[-22.0, rng.uniform(3.0, 8.0, 9)])
    theta = np.linspace(-np.pi, np.pi, 540, endpoint=False)
    ring_slant = R * np.tan(np.radians(2.6)) * np.cos(theta)
    gap_slant = R * np.tan(np.radians(1.8)) * np.cos(theta - 0.3)
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c in centres:
        s = c + ring_slant + rng.normal(0.0, 0.3, theta.size)
        r = R + rng.normal(0.0, 2.0, theta.size)
        if gap:
            r += DEPTH_MM * (np.abs(s - gap_slant - GAP_AT) <= 0.5 * GAP_MM)
        rings.append((s, r))
    return _stacked(_line(centres), theta, rings)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_wide_gap_crossed_by_slanted_rings_is_one_joint(seed: int) -> None:
    line, sigma, rho, theta, frame = _scene(seed, gap=True)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    joints = [f for f in found.features if isinstance(f, Joint)]
    assert len(joints) == 1, found.features
    j = joints[0]
    assert abs(j.axial_mm - GAP_AT) <= max(3.0 * j.axial_sigma_mm, 1.0), j
    assert abs(j.gap_mm - GAP_MM) <= 3.0 * j.gap_sigma_mm, j
    assert found.not_wall[np.abs(sigma - GAP_AT) < 3.0].mean() > 0.5


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_slanted_rings_on_plain_wall_hold_no_joint(seed: int) -> None:
    line, sigma, rho, theta, frame = _scene(seed, gap=False)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    assert found.features == [], found.features


def _two_gaps(seed: int) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[tuple[float, float]]]:
    """Rings every ~6 mm over 200 mm of a 450 mm pipe, square to the pipe but tilted 5 deg
    to the fitted axis (each strays +-20 mm along the axial coordinate, as behind a
    centreline fitted off the pipe's axis: bench seed 31), wall noise 0.8 mm with 1 % of
    samples 6 mm out (their candidates link the run along the axis); two gaps 37 mm
    apart: (centre, width), 13 and 9 mm deep. A ring whose centre lies in a gap is deep
    all round (it is square to the gap)."""
    rng = np.random.default_rng(seed)
    radius = 225.0
    gaps = [(-131.0, 12.0), (-94.5, 6.0)]
    centres = -150.0 + np.cumsum(rng.uniform(5.0, 7.0, 34))
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    spread = radius * np.tan(np.radians(5.0)) * np.cos(theta - 0.4)
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c in centres:
        r = radius + rng.normal(0.0, 0.8, theta.size) + 6.0 * (rng.random(theta.size) < 0.01)
        for (g, w), depth in zip(gaps, (13.0, 9.0), strict=True):
            r += depth * (abs(c - g) <= 0.5 * w)
        rings.append((c + spread, r))
    return *_stacked(Centreline.straight(centres, radius), theta, rings), gaps


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_two_gaps_of_raised_rings_linked_along_the_run_are_two_joints(seed: int) -> None:
    line, sigma, rho, theta, frame, gaps = _two_gaps(seed)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 225.0)
    joints = sorted((f for f in found.features if isinstance(f, Joint)), key=lambda f: f.axial_mm)
    assert len(joints) == 2, found.features
    for j, (g, w) in zip(joints, gaps, strict=True):
        # Rings ~6 mm apart: the edges lie between two rings' centres.
        assert abs(j.axial_mm - g) <= max(3.0 * j.axial_sigma_mm, 3.0), (j, g)
        assert abs(j.gap_mm - w) <= max(3.0 * j.gap_sigma_mm, 3.0), (j, w)


def _offset_step(seed: int) -> tuple[Centreline, Rings]:
    """Rings every ~6 mm over 120 mm of a 300 mm pipe, square to it, wall noise 0.3 mm;
    the section beyond axial 0 displaced 6 mm sideways (an offset joint whose gap lies
    between two rings): the rings' centres step 6 mm there."""
    rng = np.random.default_rng(seed)
    radius = 150.0
    centres = -60.0 + np.cumsum(rng.uniform(5.0, 7.0, 20))
    k = len(centres)
    theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    sig = np.repeat(centres, theta.size)
    rho = radius + rng.normal(0.0, 0.3, sig.size)
    th = np.tile(theta, k)
    frame = np.repeat(np.arange(k), theta.size)
    z = np.tile([0.0, 0.0, 1.0], (k, 1))
    world = centres[:, None] * z + 6.0 * (centres > 0.0)[:, None] * np.array([1.0, 0.0, 0.0])
    line = Centreline(centres, world, z, np.tile([1.0, 0.0, 0.0], (k, 1)), np.tile([0.0, 1.0, 0.0], (k, 1)),
                      np.full(k, radius), [])
    rings = Rings(sig, rho, th, frame, frame, centres, np.zeros(sig.size), 0.3)
    return line, rings


@pytest.mark.parametrize("seed", [1, 2])
def test_offset_step_is_a_joint_unless_a_lateral_opening_is_there(seed: int) -> None:
    """The step alone is a joint (offset within 3 sigma of 6 mm); within a found
    lateral's reach it is not (a hole's samples pull its rings' section centres)."""
    line, rings = _offset_step(seed)
    found = offset_joints(FeatureConfig(), line, rings, [])
    assert len(found) == 1, found
    j = found[0]
    assert abs(j.offset_mm - 6.0) <= max(3.0 * j.offset_sigma_mm, 0.3), j
    assert abs(j.axial_mm) <= 3.0 * j.axial_sigma_mm + 3.5, j
    hole = Lateral(axial_mm=30.0, axial_sigma_mm=2.0, angle_deg=90.0, angle_sigma_deg=1.0,
                   diameter_mm=60.0, diameter_sigma_mm=2.0, points=50)
    assert offset_joints(FeatureConfig(), line, rings, [hole]) == []
    away = Lateral(axial_mm=100.0, axial_sigma_mm=2.0, angle_deg=90.0, angle_sigma_deg=1.0,
                   diameter_mm=60.0, diameter_sigma_mm=2.0, points=50)
    assert len(offset_joints(FeatureConfig(), line, rings, [away])) == 1


def _reducer(seed: int, gap: bool) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Seven rings 12 mm apart (jittered) through a 275 -> 222 mm reducer 41 mm long
    (bench seed 30), square to the pipe, wall noise 0.5 mm; with ``gap``, a joint 11 mm
    wide at -75.3 mm on the ramp, the ring at -79 lying in it raised 5 mm (seed 30's
    stood 4.5 mm above its neighbours' chord): below the flat upstream wall's level."""
    rng = np.random.default_rng(seed)
    centres = np.array([-103.4, -91.5, -79.3, -66.8, -54.3, -42.0, -29.9]) + rng.uniform(-0.5, 0.5, 7)
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    radius = np.interp(centres, [-88.0, -47.0], [137.5, 111.0])
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c, r0 in zip(centres, radius, strict=True):
        r = r0 + rng.normal(0.0, 0.5, theta.size) + (5.0 if gap and abs(c + 75.3) <= 5.5 else 0.0)
        rings.append((np.full(theta.size, c), r))
    return _stacked(Centreline.straight(centres, radius), theta, rings)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_joint_on_a_reducers_ramp_is_found_and_the_ramp_alone_is_none(seed: int) -> None:
    line, sigma, rho, theta, frame = _reducer(seed, gap=True)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 125.0)
    joints = [f for f in found.features if isinstance(f, Joint)]
    assert len(joints) == 1, found.features
    # One ring in the gap, 12 mm from the next: the joint lies between its neighbours.
    assert abs(joints[0].axial_mm + 75.3) <= max(3.0 * joints[0].axial_sigma_mm, 6.0), joints
    line, sigma, rho, theta, frame = _reducer(seed, gap=False)
    plain = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 125.0)
    assert not [f for f in plain.features if isinstance(f, Joint)], plain.features


def _crossed(seed: int, gap: bool, arc_deg: float = 360.0) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bench seed 10's geometry: 19 rings over 44 mm of a 543 mm pipe (R 271.5), each
    tilted 7.7 deg (spanning 73 mm along the axis), so every ring crosses a 3.8 mm gap
    at -191 mm along a slant, the rings' crossings sweeping 50-130 deg; water hides the
    wall at 200-320 deg (no samples), the other crossing reads shallow (near the water
    line, 150-200 deg), the deep run a ring sees
    blurred over 16 deg of its arc to 3-5 mm (400x300: 5.6 mm of wall a pixel), wall
    noise 0.9 mm, the gap read 13 mm further along the axis by the last ring than by
    the first (the camera motion's axial placement). ``arc_deg``: the gap deep over only this arc about 90 deg (a groove
    around part of the pipe, no joint) instead of wherever the rings cross it."""
    rng = np.random.default_rng(seed)
    r0, gap_at = 271.5, -191.2
    centres = np.linspace(-201.0, -157.0, 19) + rng.uniform(-0.5, 0.5, 19)
    theta = np.radians(np.r_[np.arange(0.0, 200.0, 0.67), np.arange(320.0, 360.0, 0.67)])
    slant = r0 * np.tan(np.radians(7.7)) * np.cos(theta + np.radians(24.0))  # crossings sweep 50-130 deg
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c in centres:
        s = c + slant + rng.normal(0.0, 0.3, theta.size)
        r = r0 + rng.normal(0.0, 0.9, theta.size)
        if gap:
            # The crossing's blur (a 10 mm run along the axis), where the camera motion's
            # axial placement puts it: 0.3 mm further a mm of the rings' travel.
            seen = np.abs(s - gap_at - 0.3 * (c - gap_at)) <= 5.0
            seen &= np.abs(np.degrees(theta) - 90.0) <= 0.5 * arc_deg
            r += np.where(seen & (theta < np.radians(150.0)), rng.uniform(3.0, 5.0, theta.size), 0.0)
        rings.append((s, r))
    return _stacked(_line(centres), theta, rings)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_gap_every_ring_crosses_along_a_slant_is_a_joint(seed: int) -> None:
    """Seen deep on 60-150 deg only (6-9 of the ~20 sectors the rings sample in its
    band: under joint_coverage), but by every ring along one plane: a joint, within 3
    mm of the truth; its offset unmeasured (no ring lies wholly on a side). The same
    rings without the gap: nothing; a groove over 40 deg only: no joint."""
    line, sigma, rho, theta, frame = _crossed(seed, gap=True)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 271.5)
    joints = [f for f in found.features if isinstance(f, Joint)]
    assert len(joints) == 1, found.features
    assert abs(joints[0].axial_mm + 191.2) <= 3.0, joints[0]
    assert joints[0].offset_mm is None
    # The rings blur the 3.8 mm gap over their slant: its sigma covers the truth.
    assert abs(joints[0].gap_mm - 3.8) <= 3.0 * joints[0].gap_sigma_mm, joints[0]
    for gap, arc in ((False, 360.0), (True, 40.0)):
        line, sigma, rho, theta, frame = _crossed(seed, gap=gap, arc_deg=arc)
        found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 271.5)
        assert not [f for f in found.features if isinstance(f, Joint)], found.features


def _ring_in_gap(seed: int) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rings square to a 300 mm pipe, ~10 mm apart, wall noise 0.3 mm; a joint 16 mm wide
    (-10..+6 mm), 5 mm deep, holding one ring (at 0 mm, deep all round) whose neighbours
    (-17 and +13 mm) lie beyond the gap by more than the band's own width (bench seeds 29
    and 33: one ring in an 8-12 mm gap, the next rings 7-13 mm out)."""
    rng = np.random.default_rng(seed)
    centres = np.array([-57.0, -47.0, -37.0, -27.0, -17.0, 0.0, 13.0, 23.0, 33.0, 43.0, 53.0])
    centres = centres + rng.uniform(-0.3, 0.3, centres.size)
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c in centres:
        s = c + rng.normal(0.0, 0.2, theta.size)
        r = 150.0 + rng.normal(0.0, 0.3, theta.size) + 5.0 * ((s >= -10.0) & (s <= 6.0))
        rings.append((s, r))
    return _stacked(Centreline.straight(centres, 150.0), theta, rings)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_ring_in_a_gap_places_the_edges_between_it_and_its_neighbours(seed: int) -> None:
    line, sigma, rho, theta, frame = _ring_in_gap(seed)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, 150.0)
    joints = [f for f in found.features if isinstance(f, Joint)]
    assert len(joints) == 1, found.features
    j = joints[0]
    # Each edge lies somewhere between the deep ring and the next shallow one: the
    # joint's centre and gap within 3 sigma of the truth (-2 mm, 16 mm), not the deep
    # ring's own width (the edges at its samples' median).
    assert abs(j.axial_mm + 2.0) <= 3.0 * j.axial_sigma_mm, j
    assert abs(j.gap_mm - 16.0) <= 3.0 * j.gap_sigma_mm, j
    assert j.gap_mm >= 8.0, j


def _close_pairs(seed: int) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 534 mm pipe, wall noise 0.8 mm; a 10 mm gap, 10 mm deep, holding one ring (at
    0 mm), its downstream section displaced 2.3 mm; a side's other rings two, 0.5 mm apart,
    20 mm out (bench seed 13: few rings a side, which leave the local axis' drift poorly
    held: it trades its tilt for the step)."""
    rng = np.random.default_rng(seed)
    centres = np.array([-20.5, -20.0, 0.0, 20.0, 20.5]) + rng.normal(0.0, 0.3, 5)
    theta = np.linspace(-np.pi, np.pi, 540, endpoint=False)
    rings: list[tuple[np.ndarray, np.ndarray]] = []
    for c in centres:
        s = c + rng.normal(0.0, 0.3, theta.size)
        step = 2.3 * (c > 0)
        r = np.hypot(R * np.cos(theta) - step, R * np.sin(theta)) + rng.normal(0.0, 0.8, theta.size)
        rings.append((s, r + 10.0 * (np.abs(s) <= 5.0)))
    return _stacked(Centreline.straight(centres, R), theta, rings)


@pytest.mark.parametrize("seed", [4, 5, 7])
def test_a_local_axis_tilted_past_the_bound_is_refitted_without_drift(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    from omnipipe.analysis import joints

    line, sigma, rho, theta, frame = _close_pairs(seed)
    (kept,) = [f for f in find_features(FeatureConfig(), line, sigma, rho, theta, frame, R).features
               if isinstance(f, Joint)]
    # Here the drift tilts the local axis 3.5-7 deg: within the bound the fit is kept,
    # its step's sigma (the jackknife over four rings) over a millimetre.
    assert kept.offset_sigma_mm > 1.0, kept
    monkeypatch.setattr(joints, "LOCAL_AXIS_MAX_TILT_DEG", 3.0)
    (j,) = [f for f in find_features(FeatureConfig(), line, sigma, rho, theta, frame, R).features
            if isinstance(f, Joint)]
    # Past it: the wall along the centreline (straight here) gives the step itself.
    assert abs(j.offset_mm - 2.3) <= 3.0 * j.offset_sigma_mm, j
    assert j.offset_sigma_mm < 0.2, j
    assert abs(j.axial_mm) <= 3.0 * j.axial_sigma_mm, j
    assert abs(j.gap_mm - 10.0) <= 3.0 * j.gap_sigma_mm, j

"""Defect candidates seen by one ring with one-sided support (the run's end, the rim of a
found joint or lateral) are warnings, not defects; true defects beside them are kept."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis.defect_search import FeatureZone
from omnipipe.analysis.defects import find_defects
from omnipipe.analysis.feature_types import Joint, Lateral
from omnipipe.analysis.features import feature_zones
from omnipipe.analysis.sizing import plateau
from omnipipe.analysis.wall_profile import WallSamples

RADIUS = 100.0
CIRC = 2 * math.pi * RADIUS
KW = dict(min_height_mm=1.0, noise_factor=6, min_points=4, grid_mm=0.25)


def _wall(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rings every 5 mm from 0 to 195 mm, 720 samples each, 0.05 mm noise."""
    rng = np.random.default_rng(seed)
    sig, arc = np.meshgrid(np.arange(0, 200, 5.0), np.arange(720) * CIRC / 720, indexing="ij")
    sig, arc = sig.ravel(), arc.ravel()
    return sig, arc, rng.normal(0, 0.05, sig.size), (sig // 5).astype(int)


def _streak(sig: np.ndarray, arc: np.ndarray, ring_z: float, angle_deg: float, height: float) -> np.ndarray:
    """A 20 mm wide (around the pipe) bump of ``height`` on the one ring at ``ring_z``."""
    du = (arc - math.radians(angle_deg) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    return height * plateau(du, 20.0, 5.0) * (np.abs(sig - ring_z) < 1.0)


def _search(sig, arc, dev, ring, keep=None, zones=()):
    k = np.ones(sig.size, bool) if keep is None else keep
    return find_defects(WallSamples(sig[k], arc[k], dev[k], ring[k], CIRC), zones=zones, **KW)


@pytest.mark.parametrize("ring_z", [0.0, 195.0])
def test_one_ring_streak_at_the_run_end_is_a_warning(ring_z: float) -> None:
    """A 3 mm streak on the first (last) ring: no wall measured beyond it, flagged only;
    the same streak mid-run (rings either side measured) stays a defect."""
    sig, arc, dev, ring = _wall(11)
    res = _search(sig, arc, dev + _streak(sig, arc, ring_z, 90.0, -3.0), ring)
    assert res.defects == []
    assert sum("one-sided" in w and "no measured wall" in w for w in res.warnings) == 1
    mid = _search(sig, arc, dev + _streak(sig, arc, 100.0, 90.0, -3.0), ring)
    assert len(mid.defects) == 1 and mid.defects[0].kind == "bulge"
    assert abs(mid.defects[0].angle_deg - 90.0) < 3.0
    assert not any("one-sided" in w for w in mid.warnings)


def test_one_ring_streak_beside_an_excluded_band_is_a_warning() -> None:
    """Mid-run, but the rings before it were taken out at its angles (a joint's band, not
    wall): one-sided, flagged; the wall after the band still measured."""
    sig, arc, dev, ring = _wall(12)
    dev = dev + _streak(sig, arc, 100.0, 200.0, 3.0)
    band = (sig >= 80.0) & (sig < 100.0)
    res = _search(sig, arc, dev, ring, keep=~band)
    assert res.defects == []
    assert any("dent candidate" in w and "before it" in w for w in res.warnings)


def test_one_ring_streak_in_a_feature_zone_is_a_warning_a_true_dent_is_kept() -> None:
    """A one-ring streak inside a found lateral's zone is its rim: flagged; outside the
    zone's angles it stays a defect. A true dent 40 mm long (8 rings) inside a joint's
    zone is found and sized as without the zone (height within 0.05 mm of it, and of
    the true 2 mm within 0.3 mm)."""
    sig, arc, dev, ring = _wall(13)
    zone = FeatureZone(90.0, 110.0, "the lateral at 100.0 mm", arc_mm=math.radians(90.0) * RADIUS, half_arc_mm=25.0)
    rim = _search(sig, arc, dev + _streak(sig, arc, 100.0, 90.0, 3.0), ring, zones=[zone])
    assert rim.defects == [] and any("reach of the lateral at 100.0 mm" in w for w in rim.warnings)
    away = _search(sig, arc, dev + _streak(sig, arc, 100.0, 270.0, 3.0), ring, zones=[zone])
    assert len(away.defects) == 1 and abs(away.defects[0].angle_deg - 270.0) < 3.0

    du = (arc - math.radians(45.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    dent = dev + 2.0 * plateau(du, 18.0, 6.0) * plateau(sig - 100.0, 40.0, 10.0)
    joint = FeatureZone(60.0, 140.0, "the joint at 100.0 mm")
    with_zone = _search(sig, arc, dent, ring, zones=[joint])
    plain = _search(sig, arc, dent, ring)
    assert len(with_zone.defects) == len(plain.defects) == 1
    assert abs(with_zone.defects[0].height_mm - plain.defects[0].height_mm) < 0.05
    assert abs(with_zone.defects[0].height_mm - 2.0) < 0.3


def test_feature_zones_reach_three_sigma() -> None:
    """A joint's zone: gap / 2 + margin + 3 sigma of its edge each side, all around; a
    lateral's: its opening's arc semi-axis + margin + 3 sigma, along and around."""
    j = Joint(axial_mm=50.0, axial_sigma_mm=1.0, gap_mm=6.0, gap_sigma_mm=2.0)
    lat = Lateral(axial_mm=-20.0, axial_sigma_mm=0.5, angle_deg=90.0, angle_sigma_deg=0.0,
                  diameter_mm=40.0, diameter_sigma_mm=0.0)
    zj, zl = feature_zones([j, lat], RADIUS, 3.0)
    half = 3.0 + 3.0 + 3.0 * math.hypot(1.0, 1.0)
    assert (zj.axial_from_mm, zj.axial_to_mm, zj.arc_mm) == (pytest.approx(50.0 - half), pytest.approx(50.0 + half), None)
    b = RADIUS * math.asin(0.2)
    assert zl.axial_to_mm - zl.axial_from_mm == pytest.approx(2 * (b + 3.0 + 1.5))
    assert zl.arc_mm == pytest.approx(0.5 * math.pi * RADIUS) and zl.half_arc_mm == pytest.approx(b + 3.0)


def test_spike_deeper_than_wide_is_no_defect_but_a_dent_is() -> None:
    """Three samples 200 mm beyond the wall on two neighbouring rings (stray light off
    standing water): a warning, no defect; a 3 mm dent 20 mm wide over the same rings
    stays a defect."""
    sig, arc, dev, ring = _wall(13)
    du = (arc - math.radians(120.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    spike = (np.abs(du) < 2.0) & ((np.abs(sig - 100.0) < 1.0) | (np.abs(sig - 105.0) < 1.0))
    res = _search(sig, arc, dev + 200.0 * spike, ring)
    assert res.defects == []
    assert any("spike" in w for w in res.warnings), res.warnings
    dent = _search(sig, arc, dev + _streak(sig, arc, 100.0, 120.0, 3.0) + _streak(sig, arc, 105.0, 120.0, 3.0), ring)
    assert len(dent.defects) == 1 and dent.defects[0].kind == "dent", dent.defects


def test_bump_reaching_into_a_laterals_zone_is_its_rim_one_clear_of_it_a_dent() -> None:
    """A 4 mm bump over three rings whose samples reach into a found lateral's zone (the
    rim lit by the branch, random-features-small seeds 6, 9, 14, 31): the opening's rim,
    a warning; the same bump 30 mm along the pipe from the zone stays a dent."""
    sig, arc, dev, ring = _wall(17)
    du = (arc - math.radians(90.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    zone = FeatureZone(40.0, 90.0, "the lateral at 65.0 mm", arc_mm=math.radians(90.0) * RADIUS, half_arc_mm=20.0)

    def bump(z0: float) -> np.ndarray:
        return 4.0 * plateau(du, 20.0, 5.0) * plateau(sig - z0, 15.0, 5.0)

    rim = _search(sig, arc, dev + bump(95.0), ring, zones=[zone])
    assert rim.defects == [], rim.defects
    assert any("opening's rim" in w and "the lateral at 65.0 mm" in w for w in rim.warnings), rim.warnings
    clear = _search(sig, arc, dev + bump(125.0), ring, zones=[zone])
    assert len(clear.defects) == 1 and clear.defects[0].kind == "dent", clear.defects
    assert abs(clear.defects[0].height_mm - 4.0) < 0.3


def test_laterals_own_zones_replace_the_circular_estimate() -> None:
    """With the openings' zones (their outline's axial semi-axis), a lateral's zone is
    that one; a joint's stays its band."""
    j = Joint(axial_mm=50.0, axial_sigma_mm=1.0, gap_mm=6.0, gap_sigma_mm=2.0)
    lat = Lateral(axial_mm=-20.0, axial_sigma_mm=0.5, angle_deg=90.0, diameter_mm=40.0)
    own = FeatureZone(-60.0, 20.0, "the lateral at -20.0 mm", arc_mm=0.5 * math.pi * RADIUS, half_arc_mm=25.0)
    zones = feature_zones([j, lat], RADIUS, 3.0, [own])
    assert own in zones and len(zones) == 2
    assert next(z for z in zones if z.arc_mm is None).axial_from_mm < 50.0


def test_one_ring_streak_reaching_into_a_joints_band_is_a_warning_three_rings_a_dent() -> None:
    """A ring tilted across a joint lies on both sections (random-features-small seed 30):
    a 3 mm streak on that one ring whose samples reach into the joint's band (some
    inside, most beside it) is a warning, not a defect; without the joint it is a
    defect, and the same streak seen by three rings beside the joint stays a dent."""
    sig, arc, dev, ring = _wall(19)
    tilted = ring == 20  # the ring at 100 mm, tilted: 100 + 8 sin(theta) mm
    sig = sig.copy()
    sig[tilted] = 100.0 + 8.0 * np.sin(arc[tilted] / RADIUS)
    joint = FeatureZone(104.0, 124.0, "the joint at 114.0 mm")
    du = (arc - math.radians(30.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    streak = 3.0 * plateau(du, 20.0, 5.0)
    one = dev + streak * tilted
    z = sig[tilted & (np.abs(du) < 10.0)]
    assert z.min() < 104.0 < z.max()  # the streak's samples straddle the band's edge
    res = _search(sig, arc, one, ring, zones=[joint])
    assert res.defects == [], res.defects
    assert any("band of the joint at 114.0 mm" in w for w in res.warnings), res.warnings
    plain = _search(sig, arc, one, ring)
    assert len(plain.defects) == 1 and plain.defects[0].kind == "dent"
    three = dev + streak * np.isin(ring, [18, 19, 20])
    beside = _search(sig, arc, three, ring, zones=[joint])
    assert len(beside.defects) == 1 and beside.defects[0].kind == "dent", beside.defects
    assert abs(beside.defects[0].angle_deg - 30.0) < 3.0


def test_one_ring_streak_steeper_than_a_dent_is_stray_peaks() -> None:
    """Mid-run, rings every 5 mm: a 7 mm streak on one ring (random-features-small seeds
    14 and 31: 7-10 mm over a dozen samples of one ring, the rings either side clean) rises
    more than half the 10 mm between its clean neighbours, steeper than any dent: a
    warning, no defect. The same streak on three rings (a 20 mm long dent) is a defect."""
    sig, arc, dev, ring = _wall(23)
    steep = _search(sig, arc, dev + _streak(sig, arc, 100.0, 150.0, 7.0), ring)
    assert steep.defects == [], steep.defects
    assert any("stray peaks along one ring" in w for w in steep.warnings), steep.warnings
    du = (arc - math.radians(150.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    three = dev + 7.0 * plateau(du, 20.0, 5.0) * np.isin(ring, [19, 20, 21])
    res = _search(sig, arc, three, ring)
    assert len(res.defects) == 1 and res.defects[0].kind == "dent", res.defects


@pytest.mark.parametrize("slant_mm", [40.0, 0.0])
def test_rings_slanted_across_a_joint_mix_its_sections(slant_mm: float) -> None:
    """Rings every 5 mm, each slanted +-``slant_mm`` along the pipe (rings tilted against
    the centreline: random-features-small seed 1, 14-18 deg), a found joint's band at
    95..105 mm and a 3 mm streak on four rings, 40 mm before the band at 270 deg. Every
    one of those rings also runs through the band: it lies on both sections and its one
    profile cannot follow the step: flagged, not a defect. On square rings (slant 0) the
    same streak is a dent beside the joint, kept."""
    sig, arc, dev, ring = _wall(21)
    sig = sig + slant_mm * np.sin(arc / RADIUS)
    du = (arc - math.radians(270.0) * RADIUS + CIRC / 2) % CIRC - CIRC / 2
    streak = 3.0 * plateau(du, 40.0, 8.0) * ((ring >= 20) & (ring <= 23))
    joint = FeatureZone(95.0, 105.0, "the joint at 100.0 mm")
    res = _search(sig, arc, dev + streak, ring, zones=[joint])
    if slant_mm:
        assert res.defects == []
        assert any("slanted across the band of the joint at 100.0 mm" in w for w in res.warnings)
    else:
        assert len(res.defects) == 1 and abs(res.defects[0].angle_deg - 270.0) < 3.0

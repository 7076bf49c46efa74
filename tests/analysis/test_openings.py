"""Openings seen as lost laser returns (analysis.openings) on seeded synthetic rings."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.analysis.openings import gap_clusters, local_gaps, return_gaps

RADIUS = 150.0


def _rings(seed: int, hole: tuple[float, float, float] | None, band_deg: tuple[float, float] | None = None):
    """Rings every 5 mm over 0-200 mm, 720 samples each (angle jitter 0.05 deg); the
    samples inside ``hole`` (axial centre mm, angle deg, diameter mm: a round hole on the
    wall) and inside ``band_deg`` (on every ring) are lost."""
    rng = np.random.default_rng(seed)
    sig, th, fr = [], [], []
    for k, z in enumerate(np.arange(0.0, 200.0, 5.0)):
        t = np.linspace(0, 2 * np.pi, 720, endpoint=False) + np.radians(rng.normal(0, 0.05, 720))
        keep = np.ones(720, bool)
        if hole is not None:
            u = ((t - math.radians(hole[1]) + np.pi) % (2 * np.pi) - np.pi) * RADIUS
            keep &= (u / (0.5 * hole[2])) ** 2 + ((z - hole[0]) / (0.5 * hole[2])) ** 2 >= 1.0
        if band_deg is not None:
            d = np.degrees(t) % 360
            keep &= ~((d >= band_deg[0]) & (d <= band_deg[1]))
        sig.append(np.full(keep.sum(), z) + rng.normal(0, 0.2, keep.sum()))
        th.append(t[keep])
        fr.append(np.full(keep.sum(), k))
    return np.concatenate(sig), np.concatenate(th), np.concatenate(fr)


def _openings(sig, th, fr):
    gaps = return_gaps(sig, th, fr, RADIUS, 6.0)
    axial = {int(k): float(np.median(sig[fr == k])) for k in np.unique(fr)}
    return gap_clusters(local_gaps(gaps, th, fr, axial, 2 * RADIUS), 7.5)


def test_a_hole_is_one_opening_at_its_place_with_its_chords() -> None:
    """A 60 mm hole at 100 mm, 40 deg: one opening over the rings crossing it (the
    middle 11), centred within a ring spacing and a degree, its widest chord within a
    sample step of 60 mm; water-like lost returns on every ring (200-260 deg) are none."""
    sig, th, fr = _rings(1, (100.0, 40.0, 60.0), band_deg=(200.0, 260.0))
    found = _openings(sig, th, fr)
    assert len(found) == 1, found
    op = found[0]
    z = np.array([g.axial_mm for g in op])
    assert abs(float(np.mean(z)) - 100.0) < 5.0 and z.min() > 70.0 and z.max() < 130.0
    assert 10 <= len(op) <= 12
    c = math.degrees(math.atan2(np.mean([math.sin(g.centre) for g in op]), np.mean([math.cos(g.centre) for g in op])))
    assert abs(c - 40.0) < 1.0
    widest = max((g.width - g.step) * RADIUS for g in op)
    assert abs(widest - 60.0) < 2.0 * (2 * np.pi / 720) * RADIUS


def test_lost_returns_on_every_ring_or_in_pieces_are_no_opening() -> None:
    """A band lost along the whole run, a stretch lost on the first rings (not seen to
    close before them), and a ring broken into many pieces: nothing."""
    sig, th, fr = _rings(2, None, band_deg=(10.0, 30.0))
    assert _openings(sig, th, fr) == []
    sig, th, fr = _rings(4, (0.0, 40.0, 60.0))
    assert _openings(sig, th, fr) == []
    sig, th, fr = _rings(3, None)
    ragged = (fr >= 10) & (fr <= 12) & (np.degrees(th) % 10 < 3.0)  # 36 pieces on 3 rings
    assert return_gaps(sig[~ragged], th[~ragged], fr[~ragged], RADIUS, 6.0) == []


def _holed_rings(seed: int, strays: int, stray_z: tuple[float, ...] = (125.0,), lost_deep: bool = False):
    """Rings every 5 mm over 0-200 mm (720 samples over the circumference at RADIUS,
    wall noise 0.2 mm) with a 40 mm round hole centred at 102.5 mm (its rim 82.5-122.5
    mm): the samples inside it lost (``lost_deep``: the ring at 120 mm keeps its lost
    stretch's middle 8 samples 6 mm deep, the branch wall lit); the rings at ``stray_z``
    (past the rim) keep ``strays`` consecutive samples 3 mm deep at the hole's angle
    (the rim's image beside them, or light scattered there). Returns (ring_z, u, dev,
    frame, rings inside)."""
    rng = np.random.default_rng(seed)
    us, devs, frs, ring_z, inside = [], [], [], {}, set()
    for k, z in enumerate(np.arange(0.0, 200.0, 5.0)):
        u = (np.linspace(-np.pi, np.pi, 720, endpoint=False) + np.radians(rng.normal(0, 0.05, 720))) * RADIUS
        dev = rng.normal(0, 0.2, 720)
        keep = (u / 20.0) ** 2 + ((z - 102.5) / 20.0) ** 2 >= 1.0
        if not keep.all():
            inside.add(k)
        if lost_deep and z == 120.0:
            lit = np.argsort(np.abs(u))[:8]
            keep[lit], dev[lit] = True, 6.0
        if z in stray_z:
            dev[np.argsort(np.abs(u))[:strays]] = 3.0
        us.append(u[keep]), devs.append(dev[keep]), frs.append(np.full(keep.sum(), k))
        ring_z[k] = float(z)
    return ring_z, np.concatenate(us), np.concatenate(devs), np.concatenate(frs), inside


def test_hole_growth_stops_at_the_rim_despite_scattered_samples() -> None:
    """A ring past the rim whose samples there stray off the wall (a few: light
    scattered at the rim; many: the rim's image biasing its peaks) but none lost lies
    outside the hole: the ends stay halfway between the last ring in the hole and it."""
    from omnipipe.analysis.openings import hole_extent

    for seed in range(3):
        for strays in (3, 8, 30):
            ring_z, u, dev, fr, inside = _holed_rings(seed, strays)
            ext = hole_extent(ring_z, u, dev, fr, {min(inside), max(inside)}, 22.0, 1.0, [])
            assert ext is not None and all(ext.closed)
            # The true rim at 82.5 / 122.5 mm (main: 127.5 with 8 or 30 strays, one ring past).
            assert abs(ext.lo_mm - 82.5) < 1e-6 and abs(ext.hi_mm - 122.5) < 1e-6


def test_rings_that_lost_their_returns_count_when_the_rim_is_seen_beyond_them() -> None:
    """Grown from the hole's middle ring: the rings that only lost their returns are the
    hole's when a ring beyond them shows the rim (stray samples, none lost); ending on a
    clean ring instead, they could be a shadow past the rim and stay out. A ring with a
    lost stretch and deep samples in it is the hole's by itself."""
    from omnipipe.analysis.openings import hole_extent

    for seed in range(3):
        ring_z, u, dev, fr, _ = _holed_rings(seed, 8, stray_z=(80.0, 125.0))
        ext = hole_extent(ring_z, u, dev, fr, {20}, 22.0, 1.0, [])
        assert ext is not None and abs(ext.lo_mm - 82.5) < 1e-6 and abs(ext.hi_mm - 122.5) < 1e-6
        ring_z, u, dev, fr, _ = _holed_rings(seed, 8, stray_z=())
        ext = hole_extent(ring_z, u, dev, fr, {20}, 22.0, 1.0, [])
        assert ext is not None and abs(ext.lo_mm - 97.5) < 1e-6 and abs(ext.hi_mm - 102.5) < 1e-6
        ring_z, u, dev, fr, _ = _holed_rings(seed, 8, stray_z=(), lost_deep=True)
        ext = hole_extent(ring_z, u, dev, fr, {20}, 22.0, 1.0, [])
        assert ext is not None and abs(ext.hi_mm - 122.5) < 1e-6


def test_sparse_rings_place_the_hole_ends_by_their_last_chords() -> None:
    """Rings 10 mm apart over a 40 mm round hole centred at 103 mm (rim 83-123 mm, not
    halfway between rings): with the rings' chords given, each end lies where the
    outline closes beyond the last ring's chord (within 2 mm), not halfway to the clean
    ring beyond (85 and 125 mm: 2 mm out each). The centre is the truth's within 0.5
    mm for hole centres anywhere between two rings."""
    from omnipipe.analysis.openings import hole_extent

    for seed, centre in enumerate((103.0, 105.0, 107.5, 100.0)):
        rng = np.random.default_rng(seed)
        us, devs, frs, ring_z, chords = [], [], [], {}, {}
        for k, z in enumerate(np.arange(0.0, 200.0, 10.0)):
            u = (np.linspace(-np.pi, np.pi, 720, endpoint=False) + np.radians(rng.normal(0, 0.05, 720))) * RADIUS
            dev = rng.normal(0, 0.2, 720)
            keep = (u / 20.0) ** 2 + ((z - centre) / 20.0) ** 2 >= 1.0
            if not keep.all():
                lost = u[~keep]
                step = 2 * np.pi / 720 * RADIUS
                chords[k] = (0.5 * float(lost.max() + lost.min()), 0.5 * float(np.ptp(lost)) + 0.5 * step)
            us.append(u[keep]), devs.append(dev[keep]), frs.append(np.full(keep.sum(), k))
            ring_z[k] = float(z)
        u, dev, fr = np.concatenate(us), np.concatenate(devs), np.concatenate(frs)
        ext = hole_extent(ring_z, u, dev, fr, set(chords), 22.0, 1.0, [], inside_chords=chords)
        assert ext is not None and all(ext.closed)
        assert abs(ext.lo_mm - (centre - 20.0)) < 2.0 and abs(ext.hi_mm - (centre + 20.0)) < 2.0
        assert abs(0.5 * (ext.lo_mm + ext.hi_mm) - centre) < 0.5
        # Without the chords: halfway between the rings.
        mid = hole_extent(ring_z, u, dev, fr, set(chords), 22.0, 1.0, [])
        assert mid is not None and abs(mid.lo_mm - 5.0 * round((centre - 20.0) / 5.0)) <= 5.0


def test_a_wider_dark_band_past_the_rim_is_not_the_hole() -> None:
    """Rings past the rim that lost a stretch wider than the hole's last chord (18 mm
    either side on the rings at 125-150 mm; the hole's last ring, at 120 mm, lost 9.7
    with its branch wall lit) with no stray samples lost their light to something else:
    the growth ends at the rim, though a ring beyond them (155 mm) shows stray samples.
    A band no wider than the hole's last chord counts (the rim seen beyond it)."""
    from omnipipe.analysis.openings import hole_extent

    for seed in range(3):
        for band, hi in ((18.0, 122.5), (8.0, 152.5)):
            ring_z, u, dev, fr, _ = _holed_rings(seed, 8, stray_z=(80.0, 155.0), lost_deep=True)
            z = np.array([ring_z[k] for k in fr])
            dark = (z >= 125.0) & (z <= 150.0) & (np.abs(u) < band)
            ext = hole_extent(ring_z, u[~dark], dev[~dark], fr[~dark], {20}, 22.0, 1.0, [])
            assert ext is not None and abs(ext.lo_mm - 82.5) < 1e-6 and abs(ext.hi_mm - hi) < 1e-6

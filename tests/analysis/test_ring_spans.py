"""Each ring's points without a per-point index (analysis.ring_spans) and the return gaps
read ring by ring (analysis.openings): equal to the whole-run computations they replace,
on seeded synthetic walls in ring order (as integrated) and shuffled."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis import ring_spans
from omnipipe.analysis.openings import ReturnGap, local_gaps, return_gaps, ring_points
from omnipipe.analysis.ring_spans import (
    RingGroups,
    RingSpans,
    non_decreasing,
    ring_ids,
    sorted_unique,
)
from omnipipe.analysis.station_profiles import ring_groups

RADIUS = 150.0


def _wall(seed: int, rings: int = 40, shuffle: bool = False, hole: bool = True):
    """(sigma, theta, frame) of ``rings`` rings every 5 mm (360-720 samples each, some
    rings empty or sparse), a 50 mm hole at 100 mm / 40 deg and a lost band on a few
    rings; ``shuffle``: the points in a random order."""
    rng = np.random.default_rng(seed)
    sig, th, fr = [], [], []
    for k in range(rings):
        if k in (3, 17):
            continue  # rings without points
        n = 8 if k == 5 else int(rng.integers(360, 720))
        t = np.linspace(-np.pi, np.pi, n, endpoint=False) + rng.normal(0, 0.2 * np.pi / n, n)
        z = 5.0 * k + rng.normal(0, 0.3, n)
        keep = np.ones(n, bool)
        if hole:
            u = ((t - math.radians(40.0) + np.pi) % (2 * np.pi) - np.pi) * RADIUS
            keep &= (u / 25.0) ** 2 + ((5.0 * k - 100.0) / 25.0) ** 2 >= 1.0
        if 25 <= k <= 28:
            keep &= np.abs(t - 2.0) > 0.2
        sig.append(z[keep])
        th.append(t[keep])
        fr.append(np.full(keep.sum(), k))
    sigma, theta, frame = np.concatenate(sig), np.concatenate(th), np.concatenate(fr).astype(np.int64)
    if shuffle:
        p = rng.permutation(len(frame))
        sigma, theta, frame = sigma[p], theta[p], frame[p]
    return sigma, theta, frame


def _ring_points_reference(frame: np.ndarray, rings: np.ndarray) -> dict[int, np.ndarray]:
    """The whole-run ring_points this module replaced (one argsort of every point)."""
    order = np.argsort(frame, kind="stable")
    sf = frame[order]
    lo, hi = np.searchsorted(sf, rings, side="left"), np.searchsorted(sf, rings, side="right")
    return {int(k): order[a:b] for k, a, b in zip(rings, lo, hi, strict=True)}


def _ring_groups_reference(frame: np.ndarray, n_rings: int) -> list[np.ndarray]:
    order = np.argsort(frame, kind="stable")
    bounds = np.searchsorted(frame[order], np.arange(n_rings + 1))
    return [order[bounds[k] : bounds[k + 1]] for k in range(n_rings)]


def _return_gaps_reference(sigma, theta, frame, radius_mm, min_arc_mm, min_steps=4.0, max_gaps=3, max_spread_rel=0.5):
    """The whole-run return_gaps this module replaced."""
    out = []
    for k, on in _ring_points_reference(frame, np.unique(frame)).items():
        if len(on) < 12 or np.ptp(sigma[on]) > max_spread_rel * radius_mm:
            continue
        o = np.argsort(np.mod(theta[on], 2.0 * math.pi))
        t = np.mod(theta[on], 2.0 * math.pi)[o]
        s = sigma[on][o]
        gaps = np.diff(np.concatenate([t, [t[0] + 2.0 * math.pi]]))
        step = float(np.median(gaps))
        wide = np.flatnonzero(gaps >= max(min_steps * step, min_arc_mm / radius_mm))
        if len(wide) > max_gaps:
            continue
        for i in wide:
            j = (i + 1) % len(t)
            out.append(ReturnGap(int(k), 0.5 * float(s[i] + s[j]), float(t[i]), float(gaps[i]), step))
    return out


def _local_gaps_reference(gaps, theta, frame, ring_axial, max_length_mm):
    rings = sorted(ring_axial, key=lambda k: ring_axial[k])
    if len(rings) < 3:
        return []
    by_ring = {k: theta[on] for k, on in _ring_points_reference(frame, np.array(rings)).items()}
    slot = {k: i for i, k in enumerate(rings)}
    out = []
    for g in gaps:
        i = slot[g.ring]
        lo = i
        while lo > 0 and not g.covers(by_ring[rings[lo - 1]]).any() and ring_axial[rings[i]] - ring_axial[rings[lo]] <= max_length_mm:
            lo -= 1
        hi = i
        while hi < len(rings) - 1 and not g.covers(by_ring[rings[hi + 1]]).any() and ring_axial[rings[hi]] - ring_axial[rings[lo]] <= max_length_mm:
            hi += 1
        if lo == 0 or hi == len(rings) - 1:
            continue
        if ring_axial[rings[hi]] - ring_axial[rings[lo]] > max_length_mm:
            continue
        out.append(g)
    return out


@pytest.fixture(autouse=True)
def _small_blocks(monkeypatch):
    """Blocks of 1,000 points: the blockwise passes cross many block edges (a ring across one)."""
    monkeypatch.setattr(ring_spans, "BLOCK", 1000)


@pytest.mark.parametrize("shuffle", [False, True])
def test_ring_indices_equal_the_whole_run_sort(shuffle: bool) -> None:
    _, _, frame = _wall(1, shuffle=shuffle)
    assert non_decreasing(frame) is (not shuffle)
    assert np.array_equal(ring_ids(frame), np.unique(frame))
    rings = np.array([0, 3, 5, 9, 17, 39, 44])  # empty rings and one past the last
    got, ref = ring_points(frame, rings), _ring_points_reference(frame, rings)
    assert list(got) == list(ref) and len(got) == len(ref)
    for k in ref:
        assert got[k].dtype == ref[k].dtype and np.array_equal(got[k], ref[k])
    groups, ref_groups = ring_groups(frame, 42), _ring_groups_reference(frame, 42)
    assert len(groups) == 42 and [len(g) for g in groups] == [len(g) for g in ref_groups]
    assert all(np.array_equal(a, b) for a, b in zip(groups, ref_groups, strict=True))
    assert np.array_equal(groups[-1], ref_groups[-1])
    with pytest.raises(IndexError):
        groups[42]


def test_a_ring_ordered_frame_is_read_in_views_not_copied() -> None:
    sigma, _, frame = _wall(2)
    spans = RingSpans(frame)
    assert spans.order is None
    i = int(np.flatnonzero(spans.rings == 10)[0])
    view = spans.values(i, sigma)
    assert np.shares_memory(view, sigma) and np.array_equal(view, sigma[frame == 10])
    picked = RingGroups(frame, np.array([12, 4]))
    assert len(picked) == 2 and np.array_equal(picked[0], np.flatnonzero(frame == 12))
    assert not non_decreasing(np.array([0, 1, 1, 2, 1]))
    assert np.array_equal(sorted_unique(np.array([2, 2, 3, 3, 3, 7])), [2, 3, 7])


@pytest.mark.parametrize("seed, shuffle", [(3, False), (4, True), (5, False)])
def test_return_and_local_gaps_equal_the_whole_run_reference(seed: int, shuffle: bool) -> None:
    """Every gap and every local gap the same floats in the same order, with and without
    ``lit`` (the stray samples out: the reference takes the copies the caller made)."""
    sigma, theta, frame = _wall(seed, shuffle=shuffle)
    rng = np.random.default_rng(seed)
    stray = rng.random(len(frame)) < 0.02
    axial = {int(k): 5.0 * float(k) for k in np.unique(frame)}
    ref = _return_gaps_reference(sigma, theta, frame, RADIUS, 6.0)
    assert len(ref) >= 6  # the hole's chords and the band
    assert return_gaps(sigma, theta, frame, RADIUS, 6.0) == ref
    assert local_gaps(ref, theta, frame, axial, 2 * RADIUS) == _local_gaps_reference(ref, theta, frame, axial, 2 * RADIUS)
    lit = ~stray
    s, t, f = sigma[lit], theta[lit], frame[lit]
    ref_lit = _return_gaps_reference(s, t, f, RADIUS, 6.0)
    got_lit = return_gaps(sigma, theta, frame, RADIUS, 6.0, lit=lit)
    assert got_lit == ref_lit and got_lit != ref
    assert local_gaps(got_lit, theta, frame, axial, 2 * RADIUS, lit=lit) == _local_gaps_reference(
        ref_lit, t, f, axial, 2 * RADIUS
    )


@pytest.mark.parametrize("shuffle", [False, True])
def test_ring_angles_equal_the_whole_run_dict(shuffle: bool) -> None:
    """_closed_openings' wall angles per ring, read when asked, equal the dict of them."""
    from omnipipe.analysis.openings import ring_angles

    sigma, theta, frame = _wall(6, shuffle=shuffle)
    wall = np.abs(sigma - 5.0 * frame) <= 0.2
    rings = np.unique(frame)
    ref = {k: theta[on[wall[on]]] for k, on in _ring_points_reference(frame, rings).items()}
    got = ring_angles(frame, rings, theta, wall)
    assert list(got) == list(ref)
    assert all(np.array_equal(got[k], ref[k]) for k in ref) and sum(len(v) for v in ref.values()) < len(theta)


def test_straightness_takes_no_square_factor() -> None:
    """The thin SVD's line equals the full SVD's to the last digit, and 4,000 stations'
    straightness allocates under 1 MB (the full SVD's (K, K) factor: 128 MB)."""
    import tracemalloc

    from omnipipe.analysis.centreline import Centreline

    rng = np.random.default_rng(7)
    for k in (3, 5, 40, 900):
        centre = np.outer(np.linspace(0, 900, k), [0.3, 0.1, 1.0]) + rng.normal(0, 0.5, (k, 3))
        line = Centreline.straight(np.linspace(0, 900, k), 80.0)
        line = type(line)(**{**line.__dict__, "centre": centre})
        c = centre - centre.mean(axis=0)
        vt = np.linalg.svd(c)[2]
        assert line.straightness_mm() == float(np.max(np.linalg.norm(c - np.outer(c @ vt[0], vt[0]), axis=1)))
    big = type(line)(**{**line.__dict__, "centre": rng.normal(0, 1, (4000, 3))})
    tracemalloc.start()
    big.straightness_mm()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1 << 20

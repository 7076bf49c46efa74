"""``joints._without_sector_rings`` and ``features._one_hole`` reading each ring's own points
(:class:`~omnipipe.analysis.ring_spans.RingSpans`) decide as the whole-run code did: rings
in run order and shuffled, with and without a lateral's opening beside a joint, pieces of
an opening with and without wall between them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis.feature_rings import FeatureConfig, Rings
from omnipipe.analysis.joints import _without_sector_rings


def _whole_run(config: FeatureConfig, r: Rings, members: np.ndarray, group: np.ndarray) -> np.ndarray:
    """The whole-run code (every point's sector, a mask of the run's points per ring): the
    reference."""
    bins = (np.degrees(r.theta) % 360 // 10).astype(int)
    rings = r.frame[members]
    narrow = []
    for k in np.unique(rings):
        seen_k = np.unique(bins[r.frame == k])
        have_k = np.unique(bins[members[rings == k]])
        if len(have_k) < 0.5 * config.joint_coverage * len(seen_k):
            narrow.append(k)
    if not narrow or len(narrow) == len(np.unique(rings)):
        return group
    is_narrow = np.isin(rings, narrow)
    sector = np.unique(bins[members[is_narrow]])
    seen = np.unique(bins[np.isin(r.frame, np.unique(rings))])
    if len(sector) > (1.0 - config.joint_coverage) * len(seen):
        return group
    lo, hi = np.percentile(r.sigma[members[~is_narrow]], [2.0, 98.0])
    s = r.sigma[members]
    beyond = is_narrow & ((s < lo - config.margin_mm) | (s > hi + config.margin_mm))
    reach = config.lateral_reach_rel * 2.0 * float(np.median(r.rho))
    if not beyond.any() or float(np.max(r.dev[members[beyond]])) < reach:
        return group
    return group[~beyond]


def _run(rng: np.random.Generator, shuffle: bool, opening_dev: float) -> tuple[Rings, np.ndarray]:
    """40 rings 2 mm apart of a 50 mm radius wall (theta over the whole circle; a few rings
    see only part of it), and the candidates of a joint (rings 10-12, deep all round) and
    of an opening (rings 16-20, a 40-degree sector, ``opening_dev`` mm out)."""
    n_rings, per = 40, 360
    frame = np.repeat(np.arange(n_rings), per)
    theta = rng.uniform(-np.pi, np.pi, len(frame))
    theta[frame == 30] = rng.uniform(0.0, 2.0, per)  # a ring that sees part of the wall
    sigma = 2.0 * frame + rng.normal(0, 0.2, len(frame))
    rho = 50.0 + rng.normal(0, 0.05, len(frame))
    dev = rng.normal(0, 0.05, len(frame))
    joint = (frame >= 10) & (frame <= 12)
    opening = (frame >= 16) & (frame <= 20) & (theta > 0.5) & (theta < 0.5 + np.radians(40))
    dev[joint] += 2.0
    dev[opening] += opening_dev
    if shuffle:
        order = rng.permutation(len(frame))
        frame, theta, sigma, rho, dev = frame[order], theta[order], sigma[order], rho[order], dev[order]
    r = Rings(sigma, rho, theta, frame, frame.copy(), 2.0 * np.arange(n_rings), dev, 0.05)
    return r, np.flatnonzero(dev > 1.0)


@pytest.mark.parametrize("shuffle", [False, True])
@pytest.mark.parametrize("opening_dev", [12.0, 3.0])  # reaching as a lateral's, or not
def test_sector_rings_as_the_whole_run_code(shuffle: bool, opening_dev: float) -> None:
    config = FeatureConfig()
    for seed in range(4):
        r, members = _run(np.random.default_rng(seed), shuffle, opening_dev)
        group = np.arange(len(members)) + 100  # positions, as _joint_bands passes them
        want = _whole_run(config, r, members, group)
        got = _without_sector_rings(config, r, members, group)
        np.testing.assert_array_equal(got, want)
        if opening_dev > 10:  # the opening's candidates dropped, the joint's kept
            assert len(got) < len(group)
            assert np.all(r.frame[members[got - 100]] <= 12)
        else:
            assert len(got) == len(group)


def test_sector_rings_of_random_subsets_as_the_whole_run_code() -> None:
    config = FeatureConfig()
    rng = np.random.default_rng(7)
    r, _ = _run(rng, True, 12.0)
    for _ in range(20):
        members = np.sort(rng.choice(len(r.frame), rng.integers(1, 3000), replace=False))
        group = np.arange(len(members))
        np.testing.assert_array_equal(
            _without_sector_rings(config, r, members, group), _whole_run(config, r, members, group)
        )


def _one_hole_whole_run(r: Rings, a: np.ndarray, b: np.ndarray, low: float) -> bool:
    """``features._one_hole`` on whole-run arrays (every point's arc, a mask of the run's
    points per ring): the reference."""
    if (a & b).any():
        return True
    za, zb = r.sigma[a], r.sigma[b]
    over = min(za.max(), zb.max()) - max(za.min(), zb.min())
    if over < 0.5 * min(np.ptp(za), np.ptp(zb)):
        return False
    ca = math.atan2(float(np.mean(np.sin(r.theta[a]))), float(np.mean(np.cos(r.theta[a]))))
    u = (r.theta - ca + np.pi) % (2 * np.pi) - np.pi
    shared = np.intersect1d(r.frame[a], r.frame[b])
    if not len(shared):
        return False
    walled = 0
    for k in shared:
        ua, ub = u[a & (r.frame == k)], u[b & (r.frame == k)]
        lo, hi = (ua.max(), ub.min()) if np.median(ua) < np.median(ub) else (ub.max(), ua.min())
        between = (r.frame == k) & (u > lo) & (u < hi) & ~a & ~b
        walled += bool(np.any(between & (np.abs(r.dev) <= low)))
    return 2 * walled < len(shared)


@pytest.mark.parametrize("shuffle", [False, True])
def test_one_hole_ring_by_ring_as_the_whole_run_code(shuffle: bool) -> None:
    from omnipipe.analysis.features import _one_hole

    rng = np.random.default_rng(21 + shuffle)
    outcomes = set()
    for trial in range(60):
        r, _ = _run(rng, shuffle, 12.0)
        k0 = int(rng.integers(0, 30))
        rings = (r.frame >= k0) & (r.frame < k0 + int(rng.integers(2, 9)))
        c = rng.uniform(-np.pi, np.pi)
        d = (r.theta - c + np.pi) % (2 * np.pi) - np.pi
        gap = rng.uniform(0.0, 0.6) if trial % 3 else 0.0  # a gap between the pieces, or none
        a = rings & (d > -0.8) & (d < -gap / 2)
        b = rings & (d > gap / 2) & (d < 0.8)
        if trial % 4 == 0:  # lit inside: no wall between the pieces on some rings
            r.dev[rings & (np.abs(d) < gap / 2) & (r.frame % 2 == 0)] += 5.0
        if trial % 5 == 0:
            b = b & (r.frame > k0 + 1)  # partly other rings
        if not a.any() or not b.any():
            continue
        got = _one_hole(r, a, b, 0.5)
        assert got == _one_hole_whole_run(r, a, b, 0.5)
        outcomes.add(got)
    assert outcomes == {True, False}  # both answers reached


def _unseen_gap_whole(sigma: np.ndarray, block: int) -> float:
    """``features._unseen_gap`` through the whole sorted copy: the reference."""
    if len(sigma) < 2:
        return 0.0
    s = np.sort(sigma)
    return float(np.max([np.max(np.diff(s[a : a + block + 1])) for a in range(0, len(s) - 1, block)]))


@pytest.mark.parametrize("block", [7, 64, 1 << 16])
def test_unseen_gap_by_value_ranges_as_the_sorted_run(monkeypatch: pytest.MonkeyPatch, block: int) -> None:
    from omnipipe.analysis import features

    monkeypatch.setattr(features, "_GAP_BLOCK", block)
    rng = np.random.default_rng(block)
    runs = [
        rng.normal(0, 50, 5000),
        np.repeat(rng.uniform(0, 100, 300), 7),  # ties
        np.concatenate([rng.uniform(0, 10, 3000), rng.uniform(40, 41, 50), [200.0]]),  # a gap, clusters
        np.round(rng.uniform(-5, 5, 4000), 1),
        np.full(500, 3.0),
        rng.normal(0, 1, 2),
    ]
    with_nan = rng.normal(0, 1, 300)
    with_nan[17] = np.nan
    with_inf = rng.normal(0, 1, 300)
    with_inf[5] = np.inf
    for sigma in [*runs, with_nan, with_inf]:
        sigma = rng.permutation(sigma)
        want, got = _unseen_gap_whole(sigma, block), features._unseen_gap(sigma)
        assert got == want or (np.isnan(got) and np.isnan(want))


def _crossed_band_whole_run(config: FeatureConfig, r: Rings, members: np.ndarray):
    """``joints._crossed_band`` with the band from the whole run's plane coordinate: the
    reference."""
    from dataclasses import replace

    from omnipipe.analysis.feature_rings import robust_sine_fit
    from omnipipe.analysis.joints import _Band

    held = np.bincount(r.ring_of[members])
    if np.count_nonzero(held) < config.joint_min_rings or held.max() > 0.5 * len(members):
        return None
    p, res, keep = robust_sine_fit(r.sigma[members], r.theta[members], 3, 2.5, 1.0)
    lo, hi = np.percentile(res[keep], [2.0, 98.0]) + p[0]
    if hi - lo > config.joint_max_gap_mm:
        return None
    if float(np.percentile(r.dev[members], 90)) >= config.lateral_reach_rel * 2.0 * float(np.median(r.rho)):
        return None
    plane = _Band(float(lo), float(hi), float(p[1]), float(p[2]))
    coord = plane.coordinate(r)
    band = (coord >= plane.lo - 0.25) & (coord <= plane.hi + 0.25)
    sect = (np.degrees(r.theta[band]) % 360 // 10).astype(int)
    seen = np.unique(sect)
    if len(seen) < 9:
        return None
    thr = 0.5 * max(config.min_depth_mm, config.joint_noise_factor * r.noise)
    deep = np.mean([np.median(r.dev[band][sect == q]) > thr for q in seen])
    if deep < 0.5:
        return None
    if plane.slant_mm > config.joint_link_mm:
        return replace(plane, crossed=True)
    return _Band(float(lo), float(hi), crossed=True)


@pytest.mark.parametrize("slant", [0.0, 1.0, 6.0])
def test_crossed_band_blockwise_as_the_whole_run_code(monkeypatch: pytest.MonkeyPatch, slant: float) -> None:
    from omnipipe.analysis.joints import _crossed_band

    config = FeatureConfig()
    rng = np.random.default_rng(int(10 * slant) + 1)
    got_any = False
    for trial in range(6):
        n_rings, per = 40, 1800  # 72,000 samples: more than one block of the band's search
        frame = np.repeat(np.arange(n_rings), per)
        theta = rng.uniform(-np.pi, np.pi, len(frame))
        sigma = 2.0 * frame + 3.0 * np.sin(theta + trial) + rng.normal(0, 0.2, len(frame))  # tilted rings
        gap = 40.0 + slant * np.cos(theta)
        dev = rng.normal(0, 0.05, len(frame))
        inside = np.abs(sigma - gap) < 1.0 + 0.3 * trial
        dev[inside] += 1.5 if trial % 3 else 0.2  # deep, or hardly (the deep share fails)
        r = Rings(sigma, 50.0 + dev, theta, frame, frame.copy(), 2.0 * np.arange(n_rings), dev, 0.05)
        members = np.flatnonzero(dev > 0.5) if trial % 3 else np.flatnonzero(inside)
        if not len(members):
            continue
        got, want = _crossed_band(config, r, members), _crossed_band_whole_run(config, r, members)
        assert got == want
        got_any |= got is not None
    assert got_any or slant == 0.0  # a band was found (not only refusals compared)


def _deep_share_whole_run(config: FeatureConfig, r: Rings, members: np.ndarray, lo: float, hi: float, raised: np.ndarray):
    """``joints._deep_share`` with each band from the whole run's coordinate and mask: the
    reference."""
    from dataclasses import replace

    from omnipipe.analysis.feature_rings import robust_sine_fit
    from omnipipe.analysis.joints import _Band

    thr = 0.5 * max(config.min_depth_mm, config.joint_noise_factor * r.noise)
    p, res, keep = robust_sine_fit(r.sigma[members], r.theta[members], 3, 2.5, 1.0)
    out = []
    lo_p, hi_p = np.percentile(res[keep], [2.0, 98.0]) + p[0]
    plane = _Band(float(lo_p), float(hi_p), float(p[1]), float(p[2]))
    for coord, a, b in ((r.sigma, lo, hi), (plane.coordinate(r), plane.lo, plane.hi)):
        band = (coord >= a - 0.25) & (coord <= b + 0.25)
        sect = (np.degrees(r.theta[band]) % 360 // 10).astype(int)
        med = np.array([np.median(r.dev[band][sect == q]) for q in np.unique(sect)])
        out.append(float(np.mean(med > thr)) if len(med) else 0.0)
    held = np.flatnonzero(np.bincount(r.ring_of[members[keep]]) >= 0.1 * keep.sum())
    if len(held) >= 2:
        return out[0], out[1], plane
    inner = len(held) == 1 and r.ring_sigma.min() < r.ring_sigma[held[0]] < r.ring_sigma.max()
    return out[0], out[1], replace(plane, ring_plane=True) if inner and raised[held].all() else None


@pytest.mark.parametrize("block", [1, 7, 1000, 1 << 16])
@pytest.mark.parametrize("shuffle", [False, True])
def test_deep_share_blockwise_as_the_whole_run_code(monkeypatch: pytest.MonkeyPatch, block: int, shuffle: bool) -> None:
    from omnipipe.analysis import joints

    monkeypatch.setattr(joints, "BAND_BLOCK", block)
    config = FeatureConfig()
    rng = np.random.default_rng(20 + block + int(shuffle))
    n_rings, per = 40, 300 if block < 1000 else 1800  # 72,000 samples: more than one block of 65,536
    seen_planes = 0
    for trial in range(5):
        frame = np.repeat(np.arange(n_rings), per)
        theta = rng.uniform(-np.pi, np.pi, len(frame))
        sigma = 2.0 * frame + 1.5 * trial * np.sin(theta + trial) + rng.normal(0, 0.2, len(frame))
        dev = rng.normal(0, 0.05, len(frame))
        theta[(frame == 3) & (theta > 0)] = np.nan  # NaN angles: in no sector
        inside = np.abs(sigma - 40.0 - trial * np.cos(theta)) < 1.0
        dev[inside] += 1.5 if trial != 2 else 0.1  # deep, or hardly
        if shuffle:
            order = rng.permutation(len(frame))
            frame, theta, sigma, dev, inside = frame[order], theta[order], sigma[order], dev[order], inside[order]
        r = Rings(sigma, 50.0 + dev, theta, frame, frame.copy(), 2.0 * np.arange(n_rings), dev, 0.05)
        members = np.flatnonzero(inside & np.isfinite(theta))
        raised = rng.random(n_rings) < 0.3
        lo, hi = float(np.percentile(sigma[members], 2)), float(np.percentile(sigma[members], 98))
        got = joints._deep_share(config, r, members, lo, hi, raised)
        want = _deep_share_whole_run(config, r, members, lo, hi, raised)
        assert got == want
        seen_planes += got[2] is not None and got[1] > 0
    assert seen_planes  # some plane's share measured (not only refusals compared)


def test_band_samples_as_the_whole_run_mask() -> None:
    from omnipipe.analysis.joints import _Band, _band_samples

    rng = np.random.default_rng(5)
    n = 10_000
    sigma, theta = rng.uniform(0, 100, n), rng.uniform(-np.pi, np.pi, n)
    sigma[::97], theta[::89] = np.nan, np.inf
    r = Rings(sigma, np.full(n, 50.0), theta, np.zeros(n, int), np.zeros(n, int), np.zeros(1), np.zeros(n), 0.05)
    for plane in (_Band(40.0, 45.0), _Band(40.0, 45.0, 3.0, -2.0)):
        coord = plane.coordinate(r)
        want = np.flatnonzero((coord >= 39.75) & (coord <= 45.25))
        for block in (1, 13, 4096, 1 << 16):
            got = _band_samples(r, plane, 39.75, 45.25, block)
            assert got.dtype == want.dtype and np.array_equal(got, want)
    empty = Rings(*(np.zeros(0) for _ in range(3)), np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), 0.05)
    assert len(_band_samples(empty, _Band(0.0, 1.0), 0.0, 1.0)) == 0

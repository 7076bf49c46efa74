"""The analysis' per-point work done a block or a ring at a time gives the numbers of the
whole-array code: pipe coordinates, the rings' section centres, the rings' points."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis import centreline
from omnipipe.analysis.axis_fit import _RingPoints, _section_centres
from omnipipe.analysis.centreline import fit_centreline
from omnipipe.analysis.records import AnalysisConfig, section_config
from omnipipe.analysis.station_profiles import ring_groups
from omnipipe.analysis.stations import ring_cut, section_order
from omnipipe.analysis.wall_profile import fit_wall_profile


def _bent_run(rng: np.random.Generator, k: int = 25, per_ring: int = 300):
    """Points (N, 3), their rings (N,, interleaved as a run's are not) and each ring's axis
    guess (K, 3) of a 40 mm radius pipe bent on 400 mm, 0.05 mm noise."""
    pts, ring, axes = [], [], []
    for i, phi in enumerate(np.linspace(0.0, 0.6, k)):
        centre = np.array([400.0 * (1 - np.cos(phi)), 0.0, 400.0 * np.sin(phi)])
        normal = np.array([np.cos(phi), 0.0, -np.sin(phi)])
        theta = rng.uniform(0, 2 * np.pi, per_ring)
        r = 40.0 + 0.3 * np.cos(2 * theta)
        p = centre + r[:, None] * (np.cos(theta)[:, None] * normal + np.sin(theta)[:, None] * [0, 1, 0])
        pts.append(p + rng.normal(0, 0.05, p.shape))
        ring.append(np.full(per_ring, i))
        axes.append([np.sin(phi), 0.0, np.cos(phi)])
    order = rng.permutation(k * per_ring)
    return np.concatenate(pts)[order], np.concatenate(ring)[order], np.array(axes)


def _whole_coordinates(line, p, station):
    """The whole-array formula (the block code's reference)."""
    q = p - line.centre[station]
    t = line.tangent[station]
    along = np.einsum("ij,ij->i", q, t)
    perp = q - along[:, None] * t
    theta = np.arctan2(
        np.einsum("ij,ij->i", perp, line.binormal[station]), np.einsum("ij,ij->i", perp, line.normal[station])
    )
    return line.arc_mm[station] + along, np.linalg.norm(perp, axis=1), theta


@pytest.fixture
def run():
    pts, ring, axes = _bent_run(np.random.default_rng(11))
    line = fit_centreline([pts[ring == k] for k in range(len(axes))], axes, np.eye(4), window_mm=30.0, loss_scale_mm=0.3)
    return pts, ring, axes, line


def test_coordinates_in_blocks_equal_the_whole_array(run, monkeypatch) -> None:
    pts, ring, _, line = run
    whole = _whole_coordinates(line, pts, ring)
    monkeypatch.setattr(centreline, "COORDINATE_BLOCK", 1000)  # 7.5 blocks, the last one short
    blocked = line.coordinates(pts, ring)
    for a, b in zip(whole, blocked, strict=True):
        assert np.array_equal(a, b)
    # and the pipe: radius 40 +- 0.3 cos 2 theta about the fitted axis
    assert np.all(np.abs(blocked[1] - 40.0) < 0.6)


def test_section_centres_ring_by_ring_equal_those_of_the_whole_run(run) -> None:
    pts, ring, _, line = run
    config = AnalysisConfig()
    _, rho, theta = _whole_coordinates(line, pts, ring)
    expected = np.zeros((len(line.arc_mm), 2))
    for i, on in enumerate(ring_groups(ring, len(line.arc_mm))):
        cut, coverage = ring_cut(theta[on], section_config(config))
        order = section_order(cut, coverage, config.profile_order, section_config(config))
        if order >= 1:
            expected[i] = fit_wall_profile(theta[on], rho[on], order, config.loss_scale_mm)[1:3]
    got = _section_centres(config, line, pts, ring)
    assert np.array_equal(got, expected)
    assert np.any(got != 0.0) and np.all(np.abs(got) < 0.5)  # centred on the fitted axis
    from omnipipe.executor import open_executor

    with open_executor(2) as ex:  # a few rings a task on two workers: the same numbers
        assert np.array_equal(_section_centres(config, line, pts, ring, ex), expected)


def test_ring_points_gathered_when_indexed_fit_the_same_centreline(run) -> None:
    pts, ring, axes, line = run
    rings = _RingPoints(pts, ring_groups(ring, len(axes)))
    assert len(rings) == len(axes)
    for k, r in enumerate(rings):
        assert np.array_equal(r, pts[ring == k])
    lazy = fit_centreline(rings, axes, np.eye(4), window_mm=30.0, loss_scale_mm=0.3)
    assert np.array_equal(lazy.centre, line.centre) and np.array_equal(lazy.radius_mm, line.radius_mm)


def _whole_supported(samples, value, sc):
    """The whole-array neighbour test (the block code's reference)."""
    arc, circ = samples.arc_mm, samples.circumference_mm
    order = np.lexsort((arc, samples.ring))
    prev_i, next_i = np.roll(order, 1), np.roll(order, -1)
    out = np.zeros(len(value), bool)
    for nb in (prev_i, next_i):
        close = (samples.ring[nb] == samples.ring[order]) & (
            np.abs((arc[nb] - arc[order] + 0.5 * circ) % circ - 0.5 * circ) <= 2.5 * sc.du / 3.0
        )
        out[order] |= close & (value[nb] > 0.5 * sc.threshold)
    return out


@pytest.mark.parametrize("rings", [1, 40])
@pytest.mark.parametrize("shuffled", [True, False])
@pytest.mark.parametrize("block", [1000, 100, 1 << 16])
def test_supported_in_blocks_equals_the_whole_array(monkeypatch, rings: int, shuffled: bool, block: int) -> None:
    """Rings of 360 samples (shuffled, or in ring order as a run's; 0.1 mm noise) with
    lone spikes and a 3-sample bump each: blocks of whole rings (about 1,000 samples;
    100: a ring each; one block) give the whole array's answer for both signs, and a
    spike without a raised neighbour is unsupported while the bump's samples are (and
    the samples either side of arc 0 only on a run of one ring)."""
    from omnipipe.analysis import defect_search
    from omnipipe.analysis.wall_profile import WallSamples

    rng = np.random.default_rng(3)
    circ = 2 * np.pi * 100.0
    arc = np.tile(np.arange(360) * circ / 360, rings) + rng.uniform(0, 0.1, 360 * rings)
    ring = np.repeat(np.arange(rings), 360)
    dev = rng.normal(0, 0.1, arc.size)
    spikes = np.arange(rings) * 360 + 50
    bump = (np.arange(rings) * 360 + 200)[:, None] + np.arange(3)
    dev[spikes] = 3.0
    dev[bump.ravel()] = 3.0
    seam = np.arange(rings)[:, None] * 360 + [0, 359]  # raised either side of a ring's arc 0
    dev[seam.ravel()] = 3.0
    dev[rng.choice(arc.size, 40, replace=False)] = -3.0  # bulge spikes, some beside each other
    order = rng.permutation(arc.size) if shuffled else np.arange(arc.size)
    samples = WallSamples(np.repeat(np.arange(rings) * 5.0, 360)[order], arc[order] % circ, dev[order], ring[order], circ)
    sc = defect_search.scales(samples, 1.0, 6.0)
    monkeypatch.setattr(defect_search, "SUPPORT_BLOCK", block)
    for sign in (1.0, -1.0):
        value = sign * samples.deviation_mm
        whole = np.flatnonzero((value > sc.threshold) & _whole_supported(samples, value, sc))
        blocked = defect_search._supported_beyond(samples, sign, sc)
        assert np.array_equal(blocked, whole)
    where = np.argsort(order)  # the shuffled position of each original sample
    got = np.zeros(arc.size, bool)
    got[defect_search._supported_beyond(samples, 1.0, sc)] = True
    assert not got[where[spikes]].any() and got[where[bump.ravel()]].all()
    # Across arc 0 only a run of one ring's first and last samples are neighbours.
    assert got[where[seam.ravel()]].all() if rings == 1 else not got[where[seam.ravel()]].any()

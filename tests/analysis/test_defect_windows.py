"""The defect search reads each candidate's window as a slice of the samples sorted along
the pipe: the same defects, sizes, sigmas, warnings and masks as the whole-run arrays.

Synthetic walls (no rendering): rings every 5 mm tilted across the pipe (a ring's samples
spread 6 mm along it, so rings overlap in axial position), samples shuffled, 0.08 mm
noise, bulges and dents of the simulator's shape, and a few one-ring streaks.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis import defect_fit, defect_search, defects, wall_profile
from omnipipe.analysis.defects import find_defects
from omnipipe.analysis.sizing import fit_bump, plateau
from omnipipe.analysis.wall_profile import WallSamples
from omnipipe.contract import Defect

RADIUS = 60.0
CIRC = 2 * np.pi * RADIUS
KW = {"min_height_mm": 1.0, "noise_factor": 6.0, "min_points": 4, "grid_mm": 0.25}


def _wall(seed: int, rings: int = 40, per_ring: int = 300) -> WallSamples:
    """A shuffled deviation map with 3-5 random bulges and dents and two one-ring streaks."""
    rng = np.random.default_rng(seed)
    arc = (np.arange(per_ring) * CIRC / per_ring)[None, :] + rng.uniform(0, 1.0, (rings, 1))
    tilt = rng.uniform(-3.0, 3.0, (rings, 1)) * np.sin(arc / RADIUS + rng.uniform(0, 6.3, (rings, 1)))
    sig = (np.arange(rings) * 5.0)[:, None] + rng.normal(0, 0.3, (rings, 1)) + tilt
    arc, sig = (arc % CIRC).ravel(), sig.ravel()
    ring = np.repeat(np.arange(rings), per_ring)
    dev = rng.normal(0, 0.08, arc.size)
    for _ in range(int(rng.integers(3, 6))):
        h, w, length = rng.uniform(1.5, 5.0), rng.uniform(8.0, 40.0), rng.uniform(8.0, 60.0)
        uc, zc = rng.uniform(0, CIRC), rng.uniform(20.0, 5.0 * rings - 20.0)
        u = (arc - uc + 0.5 * CIRC) % CIRC - 0.5 * CIRC
        sign = rng.choice([-1.0, 1.0])
        dev += sign * h * plateau(u, w, rng.uniform(0.2, 1.0) * w) * plateau(sig - zc, length, rng.uniform(0.3, 1.0) * length)
    for k in rng.choice(np.arange(3, rings - 3), 2, replace=False):  # streaks: one ring, 12 samples
        dev[k * per_ring + 100 : k * per_ring + 112] += rng.choice([-1.0, 1.0]) * 2.5
    order = rng.permutation(arc.size)
    return WallSamples(sig[order], arc[order], dev[order], ring[order], CIRC)


def _same(a, b) -> None:
    assert a.defects == b.defects and a.warnings == b.warnings
    assert len(a.masks) == len(b.masks)
    assert all(np.array_equal(m, n) for m, n in zip(a.masks, b.masks, strict=True))


@pytest.mark.parametrize("seed", [0, 1])
def test_windowed_search_equals_the_whole_run_arrays(seed: int, monkeypatch) -> None:
    """Without the axial order every window reads all samples (the whole-run arrays, the
    same exact tests): the very same search."""
    samples = _wall(seed)
    windowed = find_defects(samples, **KW)
    assert windowed.defects  # the walls hold defects to find
    monkeypatch.setattr(defects, "with_axial_order", lambda s: s)
    whole = find_defects(samples, **KW)
    _same(windowed, whole)


def _whole_run_fit(s: WallSamples, d0: Defect, sign: float, sample_spacing: float, ring_spacing: float):
    """The whole-run formulation of the candidate's fit (the windowed code's reference):
    (N,) arrays for every sample, an (N,) bool mask."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sample_spacing), max(d0.length_mm, 0.5 * ring_spacing)
    uc = d0.angle_deg / 360.0 * circ
    zc = d0.axial_start_mm + 0.5 * l0
    u = (s.arc_mm - d0.angle_deg / 360.0 * circ + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm - (d0.axial_start_mm + 0.5 * l0)
    hu = min(max(1.5 * w0, 0.5 * w0 + 10.0 * sample_spacing, 6.0), 0.45 * circ)
    hz = max(1.5 * l0, 0.5 * l0 + 3.0 * ring_spacing, 6.0)
    win = (np.abs(u) <= hu) & (np.abs(z) <= hz)
    value = sign * s.deviation_mm
    fit = fit_bump(
        u[win], z[win], value[win], s.ring[win], (d0.height_mm, 0.0, 0.0, w0, l0),
        bounds_u=(-0.5 * w0 - 2 * sample_spacing, 0.5 * w0 + 2 * sample_spacing),
        bounds_z=(-0.5 * l0 - ring_spacing, 0.5 * l0 + ring_spacing),
    )
    top = float(np.max(value[win])) if win.any() else 0.0
    if fit is not None and fit.height > top + 3.0 * fit.noise + 0.25 * top:
        fit = None
    if fit is None:
        return None, win & (value > 0.5 * d0.height_mm)
    cover = (
        plateau(u - fit.u0, fit.width, fit.ramp_u * fit.width) * plateau(z - fit.z0, fit.length, fit.ramp_z * fit.length)
    ) > 0.01
    return (fit.height, fit.width, fit.length, zc + fit.z0 - 0.5 * fit.length, (uc + fit.u0) % circ), cover


@pytest.mark.parametrize("seed", [4])
def test_each_candidates_fit_and_mask_equal_the_whole_run_reference(seed: int) -> None:
    samples = wall_profile.with_axial_order(_wall(seed))
    sc = defect_search.scales(samples, KW["min_height_mm"], KW["noise_factor"])
    fitted = 0
    for sign, kind in ((-1.0, "bulge"), (1.0, "dent")):
        for members in defect_search.clusters(samples, sc, sign, KW["min_points"]):
            d0 = defect_fit.rough_measure(samples, members, sign, kind, sc.sample_spacing, sc.typical_spacing)
            d, mask = defect_fit.fit_candidate(samples, d0, sign, sc.sample_spacing, sc.typical_spacing)
            ref, ref_mask = _whole_run_fit(samples, d0, sign, sc.sample_spacing, sc.typical_spacing)
            assert np.array_equal(mask, np.flatnonzero(ref_mask))
            unfitted = defect_fit.unfitted(samples, d0, sign, sc.sample_spacing, sc.typical_spacing)[1]
            assert np.array_equal(unfitted, np.flatnonzero(_whole_run_unfitted(samples, d0, sign, sc)))
            if ref is None:
                assert d == d0
                continue
            fitted += 1
            h, w, length, start, u = ref
            assert (d.height_mm, d.width_mm, d.length_mm, d.axial_start_mm) == (
                round(h, 3), round(w, 3), round(length, 3), round(start, 3)
            )
            assert d.angle_deg == round(u / CIRC * 360.0, 3)
            assert math.isfinite(d.height_sigma_mm)
    assert fitted >= 2


def _whole_run_unfitted(s: WallSamples, d0: Defect, sign: float, sc) -> np.ndarray:
    """(N,) the whole-run mask of an unfitted candidate: in the fit's window, above half its height."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sc.sample_spacing), max(d0.length_mm, 0.5 * sc.typical_spacing)
    u = (s.arc_mm - d0.angle_deg / 360.0 * circ + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm - (d0.axial_start_mm + 0.5 * l0)
    hu = min(max(1.5 * w0, 0.5 * w0 + 10.0 * sc.sample_spacing, 6.0), 0.45 * circ)
    hz = max(1.5 * l0, 0.5 * l0 + 3.0 * sc.typical_spacing, 6.0)
    return (np.abs(u) <= hu) & (np.abs(z) <= hz) & (sign * s.deviation_mm > 0.5 * d0.height_mm)


def test_axial_range_is_a_superset_of_the_exact_interval() -> None:
    rng = np.random.default_rng(9)
    sig = np.round(rng.uniform(-50, 50, 5000), 1)  # many ties, exactly on the bounds too
    s = wall_profile.with_axial_order(WallSamples(sig, np.zeros_like(sig), np.zeros_like(sig), np.zeros(5000, int), CIRC))
    for lo, hi in [(-10.0, 10.0), (-50.0, -49.9), (3.3, 3.3), (60.0, 70.0)]:
        got = wall_profile.axial_range(s, lo, hi)
        assert np.all(np.diff(got) > 0)
        assert set(np.flatnonzero((sig >= lo) & (sig <= hi))) <= set(got.tolist())
        assert np.all((sig[got] >= lo - 1e-6) & (sig[got] <= hi + 1e-6))


def _long_wall(rings: int, per_ring: int = 300) -> tuple[WallSamples, Defect]:
    """A plain wall of ``rings`` rings 5 mm apart (0.08 mm noise) with one 3 mm dent at
    40 mm, and the dent's rough measurement: the same window however long the run."""
    rng = np.random.default_rng(21)
    arc = np.tile(np.arange(per_ring) * CIRC / per_ring, rings)
    sig = np.repeat(np.arange(rings) * 5.0, per_ring)
    dev = rng.normal(0, 0.08, arc.size) + 3.0 * plateau(arc - 100.0, 20.0, 8.0) * plateau(sig - 40.0, 30.0, 12.0)
    samples = wall_profile.with_axial_order(WallSamples(sig, arc, dev, np.repeat(np.arange(rings), per_ring), CIRC))
    d0 = Defect(kind="dent", height_mm=3.0, width_mm=22.0, length_mm=32.0, axial_start_mm=24.0, angle_deg=100.0 / CIRC * 360.0)
    return samples, d0


def test_a_candidates_fit_holds_its_window_not_the_run() -> None:
    """The peak of the memory NumPy allocates (tracemalloc traces it) while one candidate
    is fitted and its mask made: the same on a run 10 times as long. The whole-run
    formulation allocated a dozen (N,) arrays per candidate (4.9 MB more here at 10x; an
    int32 axial order, copied whole by each ``np.searchsorted``, 0.9 MB)."""
    import tracemalloc

    defect_fit.fit_candidate(*_long_wall(40), 1.0, CIRC / 300, 5.0)  # the fit's first-call allocations
    peaks, found = [], []
    for rings in (40, 400):
        samples, d0 = _long_wall(rings)
        tracemalloc.start()
        try:
            d, mask = defect_fit.fit_candidate(samples, d0, 1.0, CIRC / 300, 5.0)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        found.append((d, mask))
    assert found[0][0] == found[1][0] and np.array_equal(found[0][1], found[1][1])
    assert found[0][0].fitted and abs(found[0][0].height_mm - 3.0) < 0.2
    assert peaks[1] < peaks[0] + 50_000, peaks

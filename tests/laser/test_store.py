"""Rings kept on disk read back equal to the rings put, in any order."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from omnipipe.laser.ring import LaserRing
from omnipipe.laser.store import RingStore
from omnipipe.spill import root_buffer


def _ring(rng: np.random.Generator, n: int, widths: int | None = None) -> LaserRing:
    """A ring of n samples; ``widths``: another length for ``peak_width_px`` (the
    triangulation filters the other arrays, not that one)."""
    return LaserRing(
        pixels=rng.normal(200, 50, (n, 2)),
        angle_rad=rng.uniform(0, 6.3, n),
        confidence=rng.uniform(3, 30, n).astype(np.float32),
        radius_sigma_px=rng.uniform(0.05, 0.3, n),
        peak_width_px=rng.uniform(1, 2, n if widths is None else widths),
        points_in_rig=rng.normal(0, 100, (n, 3)),
        sigma_mm=rng.uniform(0.01, 0.1, n),
        scanned=720,
        warnings=[f"ring of {n}"] if n % 2 else [],
    )


def _same(a: LaserRing, b: LaserRing) -> bool:
    arrays = ("pixels", "angle_rad", "confidence", "radius_sigma_px", "peak_width_px", "points_in_rig", "sigma_mm")
    return (
        all(
            getattr(a, k).dtype == getattr(b, k).dtype and np.array_equal(getattr(a, k), getattr(b, k))
            for k in arrays
        )
        and a.scanned == b.scanned
        and a.warnings == b.warnings
    )


def test_rings_read_back_as_put_in_any_order() -> None:
    rng = np.random.default_rng(3)
    rings = [_ring(rng, n, widths) for n, widths in ((50, None), (0, None), (7, 9), (300, None), (1, 0))]
    store = RingStore(len(rings))
    for i in (3, 0, 4, 1, 2):
        store.put(i, rings[i])
    assert len(store) == len(rings)
    for i in (4, 0, 3, 3, 2, 1):
        assert _same(store[i], rings[i]), f"ring {i}"
    assert all(_same(a, b) for a, b in zip(store, rings, strict=True))
    assert all(_same(a, b) for a, b in zip(store[1:4], rings[1:4], strict=True))
    # What a reader changes stays with the reader.
    store[0].pixels[:] = 0
    assert _same(store[0], rings[0])
    shifted = _ring(rng, 5)
    shifted.centroid_shift_px = rng.normal(0, 0.1, 5).astype(np.float32)
    shifted.pixels = np.asfortranarray(shifted.pixels)  # read back in C order, equal
    store2 = RingStore(2)
    store2.put(1, shifted)
    back = store2[1]
    assert _same(back, shifted) and np.array_equal(back.centroid_shift_px, shifted.centroid_shift_px)
    assert back.centroid_shift_px.dtype == np.float32 and back.pixels.flags.writeable
    with pytest.raises(ValueError, match="dimensions is not stored"):
        store2.put(0, LaserRing(np.zeros((1, 1, 1, 2)), np.zeros(1), np.zeros(1), np.zeros(1)))
    store.close()
    store2.close()


def test_a_ring_without_samples_is_kept_as_is_and_each_frame_once() -> None:
    store = RingStore(3)
    empty = _ring(np.random.default_rng(0), 0)
    store.put(0, empty)
    assert store[0] is empty
    with pytest.raises(ValueError, match="frame 0 already"):
        store.put(0, empty)
    with pytest.raises(KeyError, match="frame 2 has no ring"):
        store[2]
    store.close()


def test_a_store_restored_from_its_index_and_file_holds_the_same_rings(tmp_path) -> None:
    rng = np.random.default_rng(5)
    rings = [_ring(rng, n) for n in (40, 0, 9, 0, 120)]
    store = RingStore(len(rings) + 1)  # the last frame without a ring yet
    for i, ring in enumerate(rings):
        store.put(i, ring)
    with open(tmp_path / "copy", "wb") as fh:
        store.copy_to(fh)
    back = RingStore.restore(tmp_path / "copy", store.index())
    assert all(_same(back[i], rings[i]) for i in range(len(rings)))
    with pytest.raises(KeyError, match="frame 5 has no ring"):
        back[5]
    back.put(5, rings[0])  # the restored store goes on as the original would
    assert _same(back[5], rings[0]) and _same(back[4], rings[4])
    # An index that does not fit the file is refused, not read wrong.
    index = store.index()
    index.offset[4] = (tmp_path / "copy").stat().st_size
    with pytest.raises(ValueError, match="beyond the file"):
        RingStore.restore(tmp_path / "copy", index)
    store.close()
    back.close()


def _held_bytes(a: np.ndarray) -> int:
    """Bytes of the buffer that keeps ``a``'s values alive (its own, or the object it views)."""
    base = root_buffer(a)
    return base.nbytes if isinstance(base, np.ndarray) else len(base)


def test_each_array_read_back_holds_its_own_bytes_only() -> None:
    """An array of a ring read back keeps no other array's bytes alive: one kept (an
    empty ``gap_edges`` passed on as it is) holds what it holds, not the whole ring."""
    rng = np.random.default_rng(5)
    ring = _ring(rng, 720)
    ring.centroid_shift_px = rng.normal(0, 0.1, 720).astype(np.float32)
    store = RingStore(1)
    store.put(0, ring)
    back = store[0]
    assert back.gap_edges.shape == (0, 3) and back.gap_edges.dtype == np.float32
    for f in fields(LaserRing):
        a = getattr(back, f.name)
        if isinstance(a, np.ndarray):
            assert _held_bytes(a) == a.nbytes, f.name


def test_the_stations_rings_in_the_scratch_hold_no_memory_per_sample() -> None:
    """The analysis' ring pass (every station's ring read from the store and put in the
    run's scratch, ``ring_on_disk``) keeps per ring its arrays' objects, not its samples:
    the Python heap held grows by far less than a ring's bytes (57 KB at 720 samples)
    a ring, however many rings (no per-run copy of them)."""
    import tracemalloc

    from omnipipe.pipeline.stage_calls import ring_on_disk
    from omnipipe.spill import Pack

    rng = np.random.default_rng(6)
    n = 60
    store = RingStore(n)
    for i in range(n):
        ring = _ring(rng, 720)
        ring.centroid_shift_px = rng.normal(0, 0.1, 720).astype(np.float32)
        store.put(i, ring)
    ring_bytes = sum(getattr(ring, f.name).nbytes for f in fields(LaserRing) if f.name not in ("scanned", "warnings"))
    tracemalloc.start()
    try:
        pack = Pack()
        before = tracemalloc.get_traced_memory()[0]
        held = [ring_on_disk(pack, store[i]) for i in range(n)]
        per_ring = (tracemalloc.get_traced_memory()[0] - before) / n
    finally:
        tracemalloc.stop()
    assert len(held) == n
    assert per_ring < 0.1 * ring_bytes, f"{per_ring:.0f} bytes a ring held of {ring_bytes}"

"""omnipipe.spill: arrays kept in the run's scratch, resident only while read."""

from __future__ import annotations

import pickle
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from omnipipe.memory import release_freed_memory
from omnipipe.scratch import scratch_beside
from omnipipe.spill import Pack, drop_pages, is_on_disk, on_disk, pieces_on_disk, zeros_on_disk

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self")


def _rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as fh:
        return next(int(line.split()[1]) / 1024.0 for line in fh if line.startswith("VmRSS:"))


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64, np.int16, np.uint8, bool])
def test_on_disk_is_an_equal_writable_array(dtype) -> None:
    rng = np.random.default_rng(4)
    a = (rng.random((37, 3)) * 100).astype(dtype)
    b = on_disk(a)
    assert is_on_disk(b) and is_on_disk(b[5:9, 1]) and not is_on_disk(a)
    assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b)
    assert b.flags.writeable and b.flags.c_contiguous
    b[0, 0] = a[1, 1]
    drop_pages()  # the write survives the unmapping: it is in the file
    assert b[0, 0] == a[1, 1] and np.array_equal(a[1:], b[1:])
    back = pickle.loads(pickle.dumps(b))  # to a worker: an ordinary array
    assert not is_on_disk(back) and np.array_equal(back, b)


def test_on_disk_of_a_view_of_a_noncontiguous_array_and_edge_cases() -> None:
    a = np.arange(60.0).reshape(5, 12)[:, ::3].T  # not contiguous
    assert np.array_equal(on_disk(a), a)
    empty = np.zeros((0, 3))
    assert on_disk(empty) is empty  # nothing to keep
    record = np.zeros(1 << 16, np.uint8)  # e.g. a ring's record, its arrays views of it
    view = record[:0].view(np.float32).reshape(0, 4)
    for kept in (on_disk(view), Pack().put(view)):  # an empty view keeps not the buffer alive
        assert kept.shape == (0, 4) and kept.dtype == np.float32 and kept.base is None
    objects = np.array([None, "x"], dtype=object)
    assert on_disk(objects) is objects  # Python objects cannot live in a file
    b = on_disk(np.ones(4))
    assert on_disk(b) is b  # on disk already: not copied again
    z = zeros_on_disk((4, 5, 3), np.uint8)
    assert is_on_disk(z) and z.shape == (4, 5, 3) and z.dtype == np.uint8 and not z.any()
    assert zeros_on_disk((0, 3), float).shape == (0, 3)


def test_pieces_on_disk_are_views_of_one_file_equal_to_the_pieces() -> None:
    rng = np.random.default_rng(5)
    pieces = [rng.random((n, 2)).astype(np.float32) for n in (3, 0, 7, 1)]
    got = pieces_on_disk(pieces)
    assert len(got) == 4 and all(is_on_disk(g) for g in got if len(g))
    for p, g in zip(pieces, got, strict=True):
        assert g.dtype == p.dtype and g.shape == p.shape and np.array_equal(g, p)
    assert pieces_on_disk([]) == []


@linux_only
def test_pages_are_resident_only_while_read() -> None:
    a = np.random.default_rng(6).random(48 * 2**20 // 8)  # 48 MB
    b = on_disk(a)
    total = float(a.sum())
    del a
    drop_pages()
    low = _rss_mb()
    assert float(b.sum()) == total  # read: its pages mapped
    assert _rss_mb() > low + 40
    release_freed_memory()  # between a run's steps: unmapped again
    assert _rss_mb() < low + 8
    assert float(b.sum()) == total


@linux_only
def test_the_file_lies_in_the_runs_scratch_and_has_no_name(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with scratch_beside(out) as scratch:
        assert scratch is not None
        b = on_disk(np.arange(1000.0))
        maps = Path("/proc/self/maps").read_text().splitlines()
        ours = [line for line in maps if str(scratch) in line]
        assert ours and all(line.endswith("(deleted)") for line in ours)  # unnamed
        assert [p.name for p in scratch.iterdir() if not p.name.endswith(".json")] == []
    assert not scratch.exists()  # the scratch folder went at the end of the run ...
    assert float(b.sum()) == 499500.0  # ... the mapped file lives on with its array


@linux_only
def test_a_checkpoint_saves_the_same_archive_holding_one_arrays_pages(tmp_path: Path) -> None:
    from omnipipe.pipeline.checkpoint import _savez

    rng = np.random.default_rng(7)
    arrays = {"a0": on_disk(rng.random(32 * 2**20 // 8)), "a1": on_disk(rng.random(32 * 2**20 // 8)),
              "a2": np.arange(5, dtype=np.int16)}
    drop_pages()
    low = _rss_mb()
    with open(tmp_path / "ours.npz", "wb") as fh:
        _savez(fh, arrays)
    after = _rss_mb()
    np.savez(tmp_path / "theirs.npz", **arrays)
    # np.savez's archive, byte for byte.
    assert (tmp_path / "ours.npz").read_bytes() == (tmp_path / "theirs.npz").read_bytes()
    # Each array's pages unmapped once written (mapped, both would add 64 MB); numpy's
    # 16 MB write buffer may stay with the allocator.
    assert after < low + 40


def _sum_and_touch(a: np.ndarray) -> tuple[float, bool, bool]:
    """In a worker: the sum, whether the array arrived writable, and a write into it."""
    total = float(a.sum())
    writable = bool(a.flags.writeable)
    a.reshape(-1)[0] = -1  # its own copy: the sender's stays as it was
    return total, writable, is_on_disk(a)


@linux_only
def test_shared_on_disk_goes_to_a_local_pool_by_reference() -> None:
    from multiprocessing.reduction import ForkingPickler

    from omnipipe.executor import open_executor, ordered_map
    from omnipipe.spill import shared_on_disk

    rng = np.random.default_rng(6)
    a = rng.random((4000, 3))
    s = shared_on_disk(a)
    assert is_on_disk(s) and not s.flags.writeable and np.array_equal(s, a)
    views = [s, s[::-7, 1], s[100:300].T, s[5:6]]
    with open_executor(workers=2) as pool:
        # Sent by reference: a few hundred bytes, not the 96 KB of values.
        assert len(ForkingPickler.dumps(s)) < 1000
        assert len(ForkingPickler.dumps(np.array(s))) > a.nbytes  # an ordinary array: by value
        got = list(ordered_map(pool, _sum_and_touch, views))
    for v, (total, writable, _) in zip(views, got, strict=True):
        assert total == float(np.array(v).sum()) and writable
    assert np.array_equal(s, a)  # the workers' writes stayed theirs
    back = pickle.loads(pickle.dumps(s))  # plain pickle (e.g. Dask's): by value
    assert np.array_equal(back, a) and not is_on_disk(back)


def test_a_pack_holds_many_arrays_equal_in_few_files() -> None:
    from omnipipe.spill import Pack

    rng = np.random.default_rng(8)
    arrays = [rng.random((int(rng.integers(1, 200)), 3)) for _ in range(40)]
    arrays += [np.arange(7, dtype=np.int32), rng.random((5, 2)).astype(np.float32), np.array(3.5)]
    arrays += [np.arange(30.0).reshape(5, 6)[:, ::2]]  # not contiguous
    pack = Pack(1 << 16)
    got = [pack.put(a) for a in arrays]
    for a, g in zip(arrays, got, strict=True):
        assert is_on_disk(g) and g.flags.writeable and g.dtype == a.dtype and g.shape == a.shape
        assert np.array_equal(g, a) and g.ctypes.data % 64 == 0
    files = {id(_file_of(g)) for g in got}
    assert 1 < len(files) <= sum(a.nbytes for a in arrays) // (1 << 14) + 1  # packed, new files as they fill
    got[0][0, 0] = -1.0  # writes go to its own place only
    drop_pages()
    assert got[0][0, 0] == -1.0 and all(np.array_equal(g, a) for a, g in zip(arrays[1:], got[1:], strict=True))
    empty = np.zeros((0, 3))
    assert pack.put(empty) is empty and pack.put(got[3]) is got[3]
    big = rng.random(1 << 14)  # over a quarter of a file: a file of its own
    g = pack.put(big)
    assert is_on_disk(g) and np.array_equal(g, big) and _file_of(g) is not _file_of(got[-1])


def test_a_packs_arrays_are_one_object_each_on_the_mapping_and_pickle_by_value() -> None:
    import mmap

    from omnipipe.spill import Pack

    pack = Pack(1 << 16)
    rng = np.random.default_rng(12)
    for a in (rng.random(9), rng.random((4, 3)).astype(np.float32), np.array(2.5), rng.integers(0, 9, (2, 2, 2))):
        g = pack.put(a)
        assert isinstance(g.base, mmap.mmap) and is_on_disk(g) and g.flags.c_contiguous and g.flags.aligned
        back = pickle.loads(pickle.dumps(g))
        assert back.shape == a.shape and back.dtype == a.dtype and np.array_equal(back, a) and not is_on_disk(back)


@linux_only
def test_putting_into_a_pack_maps_none_of_its_pages() -> None:
    from omnipipe.spill import Pack

    pack = Pack()
    drop_pages()
    rng = np.random.default_rng(9)
    chunks = [rng.random(2**20 // 8) for _ in range(24)]  # 24 MB in 1 MB arrays
    low = _rss_mb()
    got = [pack.put(c) for c in chunks]
    assert _rss_mb() < low + 6
    assert all(np.array_equal(g, c) for g, c in zip(got, chunks, strict=True))


def _file_of(a: np.ndarray) -> object:
    base = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    return base.obj if isinstance(base, memoryview) else base


def _pass_over(arrays: list[np.ndarray], low: float) -> tuple[float, float]:
    """(sum of every array, the most RSS above ``low`` while reading them one by one)."""
    total, most = 0.0, 0.0
    for a in arrays:
        total += float(a.sum())
        most = max(most, _rss_mb() - low)
        time.sleep(0.01)
    return total, most


def _packed_chunks(seed: int) -> tuple[float, list[np.ndarray]]:
    """(sum of 48 random 1 MB arrays, the arrays as a :class:`~omnipipe.spill.Pack` holds them)."""
    from omnipipe.spill import Pack

    pack = Pack()
    rng = np.random.default_rng(seed)
    chunks = [rng.random(2**20 // 8) for _ in range(48)]
    return sum(float(c.sum()) for c in chunks), [pack.put(c) for c in chunks]


@linux_only
def test_a_pass_within_dropping_pages_holds_only_its_last_reads() -> None:
    from omnipipe.spill import dropping_pages

    want, got = _packed_chunks(10)
    drop_pages()
    low = _rss_mb()
    total, most = _pass_over(got, low)  # every keyframe's arrays read in turn
    assert total == want and most > 40  # without: all of them stay mapped
    drop_pages()
    low = _rss_mb()
    with dropping_pages(interval_s=0.02):
        total, most = _pass_over(got, low)
        # Written through the mapping while the thread drops pages: kept.
        z = zeros_on_disk((2**20,), np.float64)
        for a in range(0, len(z), 4096):
            z[a : a + 4096] = np.arange(a, a + 4096)
            time.sleep(0.0005)
    assert total == want and most < 16
    drop_pages()
    assert np.array_equal(z, np.arange(len(z), dtype=np.float64))


@linux_only
def test_dropping_pages_drops_a_pass_that_maps_faster_than_its_interval() -> None:
    from omnipipe.spill import dropping_pages

    want, got = _packed_chunks(11)
    drop_pages()
    low = _rss_mb()
    # An interval longer than the pass: only the growth of the resident pages drops them.
    with dropping_pages(interval_s=1000.0):
        total, most = _pass_over(got, low)
    assert total == want and most < 16
    drop_pages()
    low = _rss_mb()
    total, most = _pass_over(got, low)  # without the thread: every array stays mapped
    assert total == want and most > 40


def test_on_disk_writes_a_strided_array_a_block_at_a_time_in_c_order(monkeypatch) -> None:
    """A column, a transpose, a strided 1-D and a 3-D view go into the file a block of
    their first axis (or of values) at a time: the same values in C order."""
    import omnipipe.spill as spill

    monkeypatch.setattr(spill, "_COPY_BYTES", 40)  # many blocks, a ragged last one
    rng = np.random.default_rng(13)
    base = rng.normal(size=(37, 6))
    cases = [base[:, 1], base.T, base[::3], base.reshape(37, 3, 2)[:, ::2], np.float32(2.5) * base[::-1]]
    for a in cases:
        got = on_disk(a)
        assert got.shape == a.shape and got.dtype == a.dtype and np.array_equal(got, a)
        assert got.flags.c_contiguous and is_on_disk(got)


def test_pieces_on_disk_written_piece_by_piece_equal_the_concatenation(monkeypatch) -> None:
    import omnipipe.spill as spill

    monkeypatch.setattr(spill, "_COPY_BYTES", 64)  # pages dropped between pieces
    rng = np.random.default_rng(15)
    pieces = [on_disk(rng.random((n, 2))) if n % 2 else rng.random((n, 2)) for n in (5, 0, 40, 3, 17)]
    got = pieces_on_disk(pieces)
    whole = np.concatenate(pieces)
    assert np.array_equal(np.concatenate(got), whole) and all(g.base is not None for g in got)
    assert [g.shape for g in got] == [p.shape for p in pieces] and is_on_disk(got[0])
    assert [g.shape for g in pieces_on_disk([np.zeros((0, 2)), np.zeros((0, 2))])] == [(0, 2), (0, 2)]


def test_compressed_and_written_arrays_equal_the_whole_copies() -> None:
    """compressed_on_disk (with an in-place transform) and ScratchWriter's pieces equal the
    in-memory arrays, in the scratch; a writer given too few values refuses."""
    from omnipipe import spill

    rng = np.random.default_rng(3)
    a = rng.normal(size=3 * (spill._COPY_BYTES // 8) + 17)
    keep = rng.random(len(a)) < 0.7

    def twice(x: np.ndarray) -> np.ndarray:
        x *= 2.0
        return x

    got = spill.compressed_on_disk(a, keep, twice)
    assert spill.is_on_disk(got) and np.array_equal(got, a[keep] * 2.0)
    assert np.array_equal(spill.compressed_on_disk(a, keep), a[keep])  # a itself untouched
    assert len(spill.compressed_on_disk(a, np.zeros(len(a), bool))) == 0
    w = spill.ScratchWriter(10, np.int64)
    w.write(np.arange(4))
    w.write(np.arange(4, 10))
    out = w.array()
    assert spill.is_on_disk(out) and np.array_equal(out, np.arange(10))
    short = spill.ScratchWriter(5, float)
    short.write(np.ones(3))
    with pytest.raises(ValueError):
        short.array()

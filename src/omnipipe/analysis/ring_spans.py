"""Where each ring's points lie among a run's points, without a per-point index array.

The analysis works on a run's (N,) points and their ring indices ``frame``. Taking each
ring's points used to sort ``frame`` once (``np.argsort``, 8 bytes a point, held as
long as the rings' index arrays were: 14 MB at 2,400 continuous frames at 400x300).
The integrated points come ring after ring (:func:`omnipipe.model.integrate`), so
``frame`` never decreases and ring k's points are one slice ``[start_k, stop_k)``:
:class:`RingSpans` finds the slices' ends by binary search (``frame`` read in blocks of
:data:`BLOCK` points to check that it is sorted, never copied whole) and makes each
ring's indices when asked. A ``frame`` in any other order takes the stable sort as
before (held). Either way ring k's indices are those of ``frame == k``, ascending.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import numpy as np

BLOCK = 1 << 16
"""Points of ``frame`` read at a time by the blockwise passes (512 KB of int64)."""


def non_decreasing(frame: np.ndarray) -> bool:
    """True when the (N,) ``frame`` never decreases (checked :data:`BLOCK` at a time)."""
    last = None
    for a in range(0, len(frame), BLOCK):
        blk = frame[a : a + BLOCK]
        if (last is not None and blk[0] < last) or bool(np.any(blk[1:] < blk[:-1])):
            return False
        last = blk[-1]
    return True


def sorted_unique(frame: np.ndarray) -> np.ndarray:
    """``np.unique(frame)`` of a non-decreasing (N,) ``frame``, read :data:`BLOCK` at a
    time (no sorted copy of it)."""
    out, last = [], None
    for a in range(0, len(frame), BLOCK):
        blk = frame[a : a + BLOCK]
        first = np.empty(len(blk), bool)
        first[0] = last is None or blk[0] != last
        np.not_equal(blk[1:], blk[:-1], out=first[1:])
        out.append(blk[first])
        last = blk[-1]
    return np.concatenate(out) if out else np.unique(frame)


def ring_ids(frame: np.ndarray) -> np.ndarray:
    """``np.unique(frame)``: without a sorted copy of the (N,) ``frame`` when it never
    decreases (:func:`sorted_unique`)."""
    return sorted_unique(frame) if non_decreasing(frame) else np.unique(frame)


class RingSpans:
    """Each of ``rings``' points among the (N,) ``frame`` (default: every ring in it,
    ``np.unique(frame)``).

    Attributes:
        frame: the points' ring indices (not copied).
        rings: (R,) the rings, as given (or the sorted unique ``frame``).
        order: None when ``frame`` never decreases; otherwise its stable argsort.
        start, stop: (R,) each ring's points are ``order[start:stop]`` (or, with no
            ``order``, the indices ``start`` to ``stop``).
    """

    def __init__(self, frame: np.ndarray, rings: np.ndarray | None = None) -> None:
        self.frame = frame
        self.order = None if non_decreasing(frame) else np.argsort(frame, kind="stable")
        keys = frame if self.order is None else frame[self.order]
        if rings is None:
            rings = sorted_unique(frame) if self.order is None else np.unique(keys)
        self.rings = np.asarray(rings)
        self.start = np.searchsorted(keys, self.rings, side="left")
        self.stop = np.searchsorted(keys, self.rings, side="right")

    def __len__(self) -> int:
        return len(self.rings)

    def indices(self, i: int) -> np.ndarray:
        """The ascending indices of ring ``rings[i]``'s points (intp)."""
        a, b = int(self.start[i]), int(self.stop[i])
        return np.arange(a, b, dtype=np.intp) if self.order is None else self.order[a:b]

    def blocks(self, size: int) -> Iterator[slice | np.ndarray]:
        """The points of consecutive whole rings, about ``size`` at a time (a ring of more
        than ``size`` points alone): a slice of them when ``frame`` never decreases,
        else their indices (ring after ring, ascending within each). Made with the
        default ``rings`` (every ring), they cover every point once, in ring order."""
        i, n = 0, len(self.rings)
        while i < n:
            j = max(int(np.searchsorted(self.stop, self.start[i] + size, side="right")), i + 1)
            a, b = int(self.start[i]), int(self.stop[j - 1])
            yield slice(a, b) if self.order is None else self.order[a:b]
            i = j

    def values(self, i: int, a: np.ndarray) -> np.ndarray:
        """(M_i, ...) ``a``'s rows of ring ``rings[i]``'s points, ascending: a view of ``a``
        when ``frame`` never decreases (no copy), else gathered."""
        if self.order is None:
            return a[int(self.start[i]) : int(self.stop[i])]
        return a[self.indices(i)]


class RingIndices(Mapping[int, np.ndarray]):
    """{ring: its points' ascending indices} for the rings of a :class:`RingSpans`, each
    made when asked (equal to a dict of them, without holding them)."""

    def __init__(self, spans: RingSpans) -> None:
        self.spans = spans
        self._slot = {int(k): i for i, k in enumerate(spans.rings)}

    def __getitem__(self, k: int) -> np.ndarray:
        return self.spans.indices(self._slot[int(k)])

    def __iter__(self) -> Iterator[int]:
        return iter(self._slot)

    def __len__(self) -> int:
        return len(self._slot)


class RingGroups(Sequence[np.ndarray]):
    """(R,) the ascending indices of each of ``rings``' points (R ring indices) among the
    (N,) ``frame``, each made when indexed (equal to a list of them, without holding them)."""

    def __init__(self, frame: np.ndarray, rings: np.ndarray) -> None:
        self.spans = RingSpans(frame, np.asarray(rings))

    def __len__(self) -> int:
        return len(self.spans)

    def __getitem__(self, k: int) -> np.ndarray:  # type: ignore[override]
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        return self.spans.indices(k % len(self))

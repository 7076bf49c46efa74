"""Progress of a run: bars whose rate and ETA are honest, and the whole run's time left.

- :class:`HonestBar`: a tqdm bar whose rate is measured from its first tick on, not from
  its start: the first item carries the start-up (worker pools, compiled kernels, the
  first decode), which made tqdm's first ETA of a 4.5-minute render 1:35:36. Until a
  second tick there is no rate, and the ETA shows ``?``.
- :class:`RunEstimate`: the whole run's elapsed and remaining time. The stages still to
  come are estimated from the time the stages done so far took, scaled by their typical
  share of a run (:data:`STAGE_WEIGHTS`), so it follows the frame count and this
  machine's speed.
- :func:`reporting` / :func:`phase`: a stage reports the items of a long inner step
  (bundle windows, centreline stations, the stations' images read for the mesh) as a
  bar of its own without a progress argument through every call: ``phase(name, total)``
  returns ``tick(done)`` of the run's bars, or a no-op outside a run (and in worker
  processes).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

ProgressFactory = Callable[[str, int], Callable[[int], None]]

# Each stage's typical share of a run, relative to the decoding pass (bend, 2026-11-25,
# docs/pipeline.md: laser 5.1 s, sfm 16.9, analysis 2.4, model 4.8, output 2.1).
STAGE_WEIGHTS = {"laser": 1.0, "sfm": 3.3, "analysis": 0.47, "model": 0.94, "output": 0.41}
STAGE_ORDER = tuple(STAGE_WEIGHTS)
# The stage each bar belongs to (bars of inner steps count towards their stage).
STAGE_OF = {
    "laser": "laser", "sfm": "sfm", "bundle": "sfm", "analysis": "analysis",
    "centreline": "analysis", "defects": "analysis", "mesh": "model", "model": "model",
    "output": "output",
}


def _noop(done: int) -> None:
    return None


_REPORTERS: list[tuple[int, ProgressFactory]] = []


@contextmanager
def reporting(factory: ProgressFactory) -> Iterator[None]:
    """During the block, :func:`phase` draws through ``factory`` (in this process only)."""
    _REPORTERS.append((os.getpid(), factory))
    try:
        yield
    finally:
        _REPORTERS.pop()


def phase(name: str, total: int) -> Callable[[int], None]:
    """``tick(done)`` of a bar ``name`` over ``total`` items of the run being reported,
    or a no-op (no run, or a worker process)."""
    if _REPORTERS and _REPORTERS[-1][0] == os.getpid() and total > 0:
        return _REPORTERS[-1][1](name, total)
    return _noop


@dataclass
class Rate:
    """Items per second measured from the first tick on (the first item's start-up is
    not a rate). ``clock``: seconds (monotonic)."""

    total: int
    clock: Callable[[], float] = time.perf_counter
    _t0: float | None = None
    _n0: int = 0
    _n: int = 0
    _t: float = 0.0

    def update(self, done: int) -> None:
        now = self.clock()
        if self._t0 is None:
            self._t0, self._n0 = now, done
        self._n, self._t = done, now

    def per_second(self) -> float | None:
        """Items per second since the first tick, None before a second one."""
        if self._t0 is None or self._n <= self._n0 or self._t <= self._t0:
            return None
        return (self._n - self._n0) / (self._t - self._t0)

    def remaining_s(self) -> float | None:
        """Seconds left at that rate (0 when done), None while unknown."""
        if self._n >= self.total:
            return 0.0
        rate = self.per_second()
        if rate is None:
            return None
        return (self.total - self._n) / rate - (self.clock() - self._t)


class HonestBar(tqdm):
    """A tqdm bar whose rate and ETA come from :class:`Rate` (from its first tick on)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.honest = Rate(int(self.total or 0))

    def update(self, n: float | None = 1) -> bool | None:
        if n:
            self.honest.update(int(self.n + n))
        return super().update(n)

    @property
    def format_dict(self) -> dict[str, Any]:
        d = super().format_dict
        if hasattr(self, "honest"):
            # 0 (not None): tqdm shows '?' instead of its own average from the start.
            d["rate"] = self.honest.per_second() or 0
        return d


@dataclass
class RunEstimate:
    """The run's elapsed and remaining time from its stages' bars.

    A stage is done when a bar of a later stage starts; stages that never showed a bar
    (loaded from a checkpoint) count as done and are not used to scale. ``clock``:
    seconds (monotonic).
    """

    clock: Callable[[], float] = time.perf_counter
    t_start: float = field(default=0.0)
    _stage: str | None = None
    _stage_t0: float = 0.0
    _done: dict[str, float] = field(default_factory=dict)
    _skipped: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        if not self.t_start:
            self.t_start = self.clock()

    def bar_started(self, bar: str) -> None:
        stage = STAGE_OF.get(bar)
        if stage is None or stage == self._stage:
            return
        now = self.clock()
        if self._stage is not None:
            self._done[self._stage] = now - self._stage_t0
        later = STAGE_ORDER.index(stage)
        self._skipped |= {s for s in STAGE_ORDER[:later] if s not in self._done}
        self._stage, self._stage_t0 = stage, now

    def elapsed_s(self) -> float:
        return self.clock() - self.t_start

    def remaining_s(self, bar_left_s: float | None) -> float | None:
        """The run's seconds left, given the current bar's (None: unknown yet)."""
        if self._stage is None:
            return None
        now = self.clock()
        measured = {s: t for s, t in self._done.items() if s not in self._skipped}
        cur = self._stage
        if measured:
            scale = sum(measured.values()) / sum(STAGE_WEIGHTS[s] for s in measured)
        elif bar_left_s is not None:  # the first stage: its own projection
            scale = (now - self._stage_t0 + bar_left_s) / STAGE_WEIGHTS[cur]
        else:
            return None
        later = STAGE_ORDER[STAGE_ORDER.index(cur) + 1 :]
        # The current stage: its bar's time left, or its typical share less its time so far.
        own = bar_left_s if bar_left_s is not None else max(
            0.0, scale * STAGE_WEIGHTS[cur] - (now - self._stage_t0)
        )
        return own + scale * sum(STAGE_WEIGHTS[s] for s in later)

    def line(self, bar_left_s: float | None) -> str:
        """``run 1:23, ~4:56 left`` (``?`` while unknown)."""
        left = self.remaining_s(bar_left_s)
        told = "?" if left is None else tqdm.format_interval(max(0.0, left))
        return f"run {tqdm.format_interval(self.elapsed_s())}, ~{told} left"

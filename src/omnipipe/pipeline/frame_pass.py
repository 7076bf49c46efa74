"""The one pass that decodes every frame: light section and the stationary-frame test.

Decoding a frame costs more than anything the pass does with it (40 ms for a
1600x1200 PNG), so each frame is decoded once, in a worker of the run's executor
(:func:`omnipipe.executor.iter_frames`), which returns everything the later stages
need of it that is small:

- its laser ring, extracted and triangulated (paper Sec. III, Eq. 1-5);
- its :class:`~omnipipe.sfm.stations.StationSignature` (a box-averaged copy and the
  sensor noise), from which the parent decides, in frame order, which frames were
  taken while the robot stood still (:class:`~omnipipe.sfm.stations.StationTracker`).

Results are consumed as they arrive and the signatures are dropped once compared, so
memory does not grow with the run beyond the rings themselves. The outcome is
identical to the serial stages (:func:`omnipipe.laser.run` and the tracker fed frame
by frame).
"""

from __future__ import annotations

import math
import pickle
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.camera import camera_from_rig
from omnipipe.image import gray_without_laser
from omnipipe.laser import LaserConfig, LaserResult
from omnipipe.laser import _extractor as ring_extractor
from omnipipe.laser.extract import LaserRing
from omnipipe.laser.triangulate import triangulate_ring
from omnipipe.rig import Rig
from omnipipe.sfm.stations import (
    StationConfig,
    StationSignature,
    StationTracker,
    inner_mask,
    station_signature,
)

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.executor import FrameSource


@dataclass
class FramePassResult:
    """What the pass found in every frame, in frame order.

    Attributes:
        rings: the light-section result (one ring per frame).
        moved: (N,) True where the rig moved since the station began (a new station
            starts; frame 0 counts as moved).
        motion_ratio: (N,) the stationary test's difference over its noise-only
            expectation (inf for frame 0).
        ring_samples: (N,) accepted ring samples of each frame. A frame taken while the
            robot stood still repeats its station's ring and is used by no later stage:
            its ring is kept empty (its warnings and scan count stay), so memory grows
            with the stations, not with the time spent standing.
    """

    rings: LaserResult
    moved: np.ndarray
    motion_ratio: np.ndarray
    ring_samples: np.ndarray


# Per process: the valid-mask interior of the last rig seen (built once per worker).
_INNER: dict[bytes, np.ndarray] = {}


def _inner(rig: Rig) -> np.ndarray:
    key = pickle.dumps(rig)
    if key not in _INNER:
        _INNER.clear()
        _INNER[key] = inner_mask(camera_from_rig(rig).valid_mask())
    return _INNER[key]


class _FrameTask:
    """Picklable task: ring and station signature of each frame of one chunk."""

    def __init__(self, laser: LaserConfig, stations: StationConfig) -> None:
        self.laser = laser
        self.stations = stations

    def __call__(self, source: FrameSource) -> list[tuple[LaserRing, StationSignature]]:
        rig = source.rig
        camera, extractor = ring_extractor(self.laser, rig)
        inner = _inner(rig)
        out = []
        for k in range(len(source)):
            image = source.read(k)
            ring = triangulate_ring(extractor.extract(image, rig.laser.channel), camera, rig.laser)
            gray = gray_without_laser(image, rig.laser.channel)
            out.append((ring, station_signature(gray, inner, self.stations)))
        return out


def run(
    laser: LaserConfig,
    stations: StationConfig,
    dataset: Dataset,
    executor: Executor,
    progress: Callable[[int], None] | None = None,
) -> FramePassResult:
    """Decode every frame of ``dataset`` once: its ring and whether the rig moved.

    Args:
        laser, stations: the light-section and stationary-test settings.
        executor: from :func:`omnipipe.executor.open_executor`.
        progress: ``progress(frames_done)`` as frames arrive.

    Raises:
        DatasetError: an unreadable frame (naming its file).
    """
    from omnipipe.executor import iter_frames

    tracker = StationTracker(camera_from_rig(dataset.rig).valid_mask(), stations)
    n = len(dataset)
    rings: list[LaserRing] = []
    moved = np.zeros(n, bool)
    ratio = np.full(n, math.nan)
    samples = np.zeros(n, int)
    for i, (ring, signature) in iter_frames(executor, _FrameTask(laser, stations), dataset):
        moved[i], ratio[i] = tracker.update_signature(signature)
        samples[i] = len(ring.pixels)
        rings.append(ring if moved[i] else _emptied(ring))
        if progress is not None:
            progress(i + 1)
    warnings = [f"frame {i}: {w}" for i, ring in enumerate(rings) for w in ring.warnings]
    return FramePassResult(LaserResult(rings, warnings), moved, ratio, samples)


def _emptied(ring: LaserRing) -> LaserRing:
    """``ring`` without its samples (scan count and warnings kept)."""
    return LaserRing(
        np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0),
        scanned=ring.scanned, warnings=ring.warnings,
    )

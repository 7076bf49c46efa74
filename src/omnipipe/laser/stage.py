"""The light-section stage (paper Sec. III): metric laser-ring points of every frame.

``run(config, rig, frames)`` extracts each frame's laser ring with sub-pixel
Gaussian peak detection and intersects the rays with the calibrated laser plane.
``run_dataset(config, dataset, executor)`` does the same frame-parallel: each worker
decodes and extracts a chunk of frames (:func:`omnipipe.executor.map_frames`); the
rings are identical to the serial ones.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.executor import FrameSource, InlineExecutor, map_frames, worker_cached
from omnipipe.laser.extract import ExtractionConfig, RingExtractor
from omnipipe.laser.ring import LaserRing
from omnipipe.laser.triangulate import triangulate_ring
from omnipipe.rig import Rig

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset


@dataclass(frozen=True)
class LaserConfig:
    """Light-section settings (see :class:`ExtractionConfig`)."""

    extraction: ExtractionConfig = field(default_factory=ExtractionConfig)


@dataclass
class LaserResult:
    """Rings of all frames, in frame order.

    Attributes:
        rings: one :class:`LaserRing` per frame (pixels, points_in_rig, sigma_mm, ...):
            a list, or (from the decoding pass) a :class:`~omnipipe.laser.store.RingStore`.
        warnings: per-frame problems, prefixed with the frame index.
    """

    rings: Sequence[LaserRing]
    warnings: list[str]

    @property
    def recovered_fraction(self) -> np.ndarray:
        """(N,) fraction of scan lines with an accepted sample, per frame."""
        return np.array([r.fraction for r in self.rings])


def run(
    config: LaserConfig,
    rig: Rig,
    frames: Iterable[np.ndarray],
    progress: Callable[[int], None] | None = None,
) -> LaserResult:
    """Extract and triangulate the laser ring of every frame."""
    camera = camera_from_rig(rig)
    extractor = RingExtractor(camera, config.extraction, rig.laser)
    rings, warnings = [], []
    for i, frame in enumerate(frames):
        ring = triangulate_ring(extractor.extract(frame, rig.laser.channel), camera, rig.laser)
        warnings.extend(f"frame {i}: {w}" for w in ring.warnings)
        rings.append(ring)
        if progress:
            progress(i + 1)
    return LaserResult(rings, warnings)


def run_dataset(
    config: LaserConfig,
    dataset: Dataset,
    executor: Executor | None = None,
    progress: Callable[[int], None] | None = None,
) -> LaserResult:
    """Decode and extract the ring of every frame of ``dataset``, frame-parallel.

    Args:
        executor: from :func:`omnipipe.executor.open_executor` (None: inline, serial).
        progress: ``progress(frames_done)`` after each chunk of frames.

    Returns:
        the same :class:`LaserResult` as :func:`run` on every frame of ``dataset`` in order.

    Raises:
        DatasetError: an unreadable frame (naming its file).
    """
    task = RingTask(config)
    rings = map_frames(executor or InlineExecutor(), task, dataset, progress=progress)
    warnings = [f"frame {i}: {w}" for i, ring in enumerate(rings) for w in ring.warnings]
    return LaserResult(rings, warnings)


def ring_extractor(config: LaserConfig, rig: Rig) -> tuple[CameraModel, RingExtractor]:
    """The camera and ring extractor of ``rig`` with ``config``, built once per process
    (:func:`~omnipipe.executor.worker_cached`): a worker builds its polar sampling maps
    once, not once per chunk."""

    def build() -> tuple[CameraModel, RingExtractor]:
        camera = camera_from_rig(rig)
        return camera, RingExtractor(camera, config.extraction, rig.laser)

    return worker_cached("laser.ring_extractor", (config, rig), build)


class RingTask:
    """Picklable task: the rings (extracted and triangulated) of one chunk of frames."""

    def __init__(self, config: LaserConfig) -> None:
        self.config = config

    def __call__(self, source: FrameSource) -> list[LaserRing]:
        rig = source.rig
        camera, extractor = ring_extractor(self.config, rig)
        return [
            triangulate_ring(extractor.extract(source.read(k), rig.laser.channel), camera, rig.laser)
            for k in range(len(source))
        ]


def decode_only(source: FrameSource) -> list[tuple[int, ...]]:
    """Decode a chunk of frames and return only their shapes (benchmarks: the decode cost
    on the same workers, to compare with :func:`run_dataset`)."""
    return [tuple(source.read(k).shape) for k in range(len(source))]


class DecodeHandOn:
    """Picklable task: decode a chunk of frames and hand the ``moving`` ones ((N,) bool
    over the dataset) on to ``folder`` (a :class:`~omnipipe.handoff.FrameHandoff`'s), as
    the decoding pass does; returns their shapes (benchmarks: the floor of a laser stage
    that also hands its moving frames on to the later stages)."""

    def __init__(self, folder: str, moving: np.ndarray) -> None:
        self.folder = folder
        self.moving = np.asarray(moving, bool)

    def __call__(self, source: FrameSource) -> list[tuple[int, ...]]:
        from omnipipe.handoff import hand_on

        out = []
        for k in range(len(source)):
            image = source.read(k)
            if self.moving[int(source.frames[k])]:
                channel = None if source.rig is None else source.rig.laser.channel
                hand_on(self.folder, int(source.frames[k]), image, channel)
            out.append(tuple(image.shape))
        return out

"""The one pass that decodes every frame: light section and the stationary-frame test.

Decoding a frame costs more than anything the pass does with it (40 ms for a
1600x1200 PNG), so each frame is decoded once, in a worker of the run's executor
(:func:`omnipipe.executor.iter_frames`), which returns everything the later stages
need of it that is small:

- its laser ring, extracted and triangulated (paper Sec. III, Eq. 1-5);
- its :class:`~omnipipe.sfm.stations.StationSignature` (a box-averaged copy and the
  sensor noise), from which the parent decides, in frame order, which frames were
  taken while the robot stood still (:class:`~omnipipe.sfm.stations.StationTracker`);
- with a :class:`~omnipipe.handoff.FrameHandoff`, a moving frame as decoded (a red
  laser's colour frame planar: :class:`~omnipipe.handoff.PlanarFrame`), written
  to the run's scratch folder for the camera motion's and the model's workers, which
  then do not decode it again.

Results are consumed as they arrive and the signatures are dropped once compared; the
rings go to disk as they arrive (:class:`~omnipipe.laser.store.RingStore`), so memory
grows with the run by a few bytes a frame only (its flags and sample counts). A frame taken while the
robot stood still is used by no later stage (its station's first frame stands for
it), and most frames are such frames: the worker runs the stationary test within its
chunk too and skips the ring of a frame that shows the same station as the frame
before it (the parent fetches the rare one its own test needs after all). The
outcome is that of the serial stages (:func:`omnipipe.laser.run` and the tracker fed
frame by frame) for every frame where the rig moved, whatever the chunks.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from omnipipe.camera import camera_from_rig
from omnipipe.executor import worker_cached
from omnipipe.handoff import FrameHandoff, hand_on, handoff_full, plane_split
from omnipipe.laser import (
    LaserConfig,
    LaserResult,
    LaserRing,
    RingTask,
    ring_extractor,
    triangulate_ring,
)
from omnipipe.laser.store import RingStore
from omnipipe.rig import Rig
from omnipipe.sfm.stations import (
    StationConfig,
    StationSignature,
    StationState,
    StationTracker,
    frame_signature,
    mask_runs,
    noise_mask,
    promote_creep,
)

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.executor import FrameSource


@dataclass
class FramePassResult:
    """What the pass found in every frame, in frame order.

    Attributes:
        rings: the light-section result (one ring per frame; its ``rings`` a
            :class:`~omnipipe.laser.store.RingStore`, read from disk when indexed).
        moved: (N,) True where the rig moved since the station began (a new station
            starts; frame 0 counts as moved).
        motion_ratio: (N,) the stationary test's difference over its noise-only
            expectation (inf for frame 0).
        ring_samples: (N,) accepted ring samples of each frame. A frame taken while the
            robot stood still repeats its station's ring and is used by no later stage:
            its ring is empty, it counts its station's ring's samples and adds no
            warnings, so memory grows with the stations, not with the time spent
            standing.
    """

    rings: LaserResult
    moved: np.ndarray
    motion_ratio: np.ndarray
    ring_samples: np.ndarray


def _masks(rig: Rig, stations: StationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The valid mask, the noise estimate's pixels and their row runs, built once per
    process and (rig, settings) (:func:`~omnipipe.executor.worker_cached`)."""

    def build() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        valid = camera_from_rig(rig).valid_mask()
        inner = noise_mask(valid, stations.noise_pixels)
        return valid, inner, mask_runs(inner)

    return worker_cached("pipeline.frame_pass.masks", (rig, stations.noise_pixels), build)


def warm_up(laser: LaserConfig, stations: StationConfig, rig: Rig) -> None:
    """Build this process's per-rig tables of the pass (polar sampling maps, masks) and
    load its compiled kernels by running them once on a blank frame.

    Called before the first task is submitted: the local pool's workers are forked from
    this process and inherit both. Otherwise each worker paid for them on its first
    frame (bend, 2 workers: about 0.5 s each, half of it the compiler's start-up).
    """
    from omnipipe.inputs.png import warm_up as png_warm_up

    png_warm_up()
    camera, extractor = ring_extractor(laser, rig)
    _, inner, runs = _masks(rig, stations)
    channels = 3 if rig.laser.channel in ("red", "green", "blue") else 1
    blank = np.zeros((camera.height, camera.width, channels)[: 2 if channels == 1 else 3], np.uint8)
    extractor.extract(blank, rig.laser.channel)
    frame_signature(blank, rig.laser.channel, inner, stations, runs)


class _FrameTask:
    """Picklable task: (ring or None, station signature, bytes handed on) of each frame
    of one chunk.

    The stationary test runs within the chunk too (its own tracker, started at the
    chunk's first frame): a frame that shows the same station as the one before it in
    the chunk is all but certainly stationary for the run's tracker as well, and a
    stationary frame's ring is used by no later stage, so its extraction is skipped
    (``None``). The parent fetches the rare ring the run's tracker needs after all
    (:func:`run`), so the result never depends on where chunks begin. With
    ``handoff`` (a :class:`~omnipipe.handoff.FrameHandoff`'s folder), each frame with a
    ring is written there (:func:`~omnipipe.handoff.hand_on`; 0 bytes: not written).
    """

    def __init__(self, laser: LaserConfig, stations: StationConfig, handoff: str | None = None) -> None:
        self.laser = laser
        self.stations = stations
        self.handoff = handoff

    def __call__(self, source: FrameSource) -> list[tuple[LaserRing | None, StationSignature, int]]:
        rig = source.rig
        camera, extractor = ring_extractor(self.laser, rig)
        valid, inner, runs = _masks(rig, self.stations)
        local = StationTracker(valid, self.stations)
        out: list[tuple[LaserRing | None, StationSignature, int]] = []
        split: list[np.ndarray] = []  # the chunk's buffers of the split (fresh pages cost)
        for k in range(len(source)):
            image = source.read(k)
            planes = self._planes(image, rig.laser.channel, inner, split)
            # A red laser's grey image is the green channel: its signature is the same
            # bit for bit from the split's green plane as from the frame.
            grey_or_frame = image if planes is None else planes[1]
            signature = frame_signature(grey_or_frame, rig.laser.channel, inner, self.stations, runs)
            moved, _ = local.update_signature(signature)
            ring = (
                triangulate_ring(extractor.extract(image, rig.laser.channel), camera, rig.laser)
                if moved
                else None
            )
            written = 0
            if ring is not None and self.handoff is not None:
                written = hand_on(self.handoff, int(source.frames[k]), image, rig.laser.channel, planes)
            out.append((ring, signature, written))
        return out

    def _planes(
        self, image: np.ndarray, channel: str, inner: np.ndarray, buffers: list[np.ndarray]
    ) -> tuple[np.ndarray, ...] | None:
        """``cv2.split(image)`` when the frame would be handed on planar
        (:func:`~omnipipe.handoff.plane_split`, the hand-off not full) and its signature
        reads its green channel whole: one split serves both (it costs little more than
        the signature's own extraction of that channel); else None. The planes are
        written into ``buffers`` (made on first use, kept by the caller for its chunk's
        frames: each plane is used before the next frame is split)."""
        if (
            self.handoff is None
            or not plane_split(image, channel)
            or inner.shape != image.shape[:2]
            or handoff_full(self.handoff)
        ):
            return None
        if not buffers or buffers[0].shape != image.shape[:2]:
            buffers[:] = [np.empty(image.shape[:2], image.dtype) for _ in range(3)]
        return tuple(cv2.split(image, buffers))


@dataclass
class FramePassPart:
    """What the pass found in consecutive frames, and where its stationary test stood
    after them: a resumed run continues from the parts saved (:func:`run`).

    Attributes:
        first: the first frame's index.
        rings: each frame's ring (None: a stationary frame, or one whose ring the
            pass fetches at its end).
        moved, motion_ratio: (M,) as in :class:`FramePassResult`.
        station: (M,) each frame's station (its first frame's index).
        reference: the stationary test's state after the last frame
            (:attr:`~omnipipe.sfm.stations.StationTracker.reference`).
    """

    first: int
    rings: list[LaserRing | None]
    moved: np.ndarray
    motion_ratio: np.ndarray
    station: np.ndarray
    reference: StationState | None


# Frames between two parts handed to ``save_part`` (a few seconds of the pass).
PART_FRAMES = 256


def run(
    laser: LaserConfig,
    stations: StationConfig,
    dataset: Dataset,
    executor: Executor,
    progress: Callable[[int], None] | None = None,
    parts: Iterable[FramePassPart] = (),
    save_part: Callable[[FramePassPart], None] | None = None,
    handoff: FrameHandoff | None = None,
) -> FramePassResult:
    """Decode every frame of ``dataset`` once: its ring and whether the rig moved.

    Args:
        laser, stations: the light-section and stationary-test settings.
        executor: from :func:`omnipipe.executor.open_executor`.
        progress: ``progress(frames_done)`` as frames arrive.
        parts: the consecutive parts an earlier run of the same pass saved (from
            frame 0), taken one at a time (each one's rings go to the store before the
            next is read): the pass goes on after them, with the same result.
        save_part: called with each :data:`PART_FRAMES` frames' part as it is done.
        handoff: where the moving frames are handed on to the later stages (a local
            process pool's; None: nowhere). Frames the pass finds stationary in the
            end are removed from it.

    Raises:
        DatasetError: an unreadable frame (naming its file).
    """
    from omnipipe.executor import iter_frames

    tracker = StationTracker(_masks(dataset.rig, stations)[0], stations)  # built once (warm_up)
    n = len(dataset)
    kept = _Kept(n)
    moved = np.zeros(n, bool)
    ratio = np.full(n, math.nan)
    station = np.zeros(n, int)  # each frame's station: its first frame
    start = _restore(parts, tracker, kept, moved, ratio, station)
    if progress is not None and start:
        progress(start)
    task = _FrameTask(laser, stations, None if handoff is None else handoff.folder)
    for i, (ring, signature, written) in iter_frames(executor, task, dataset, frames=range(start, n)):
        if written and handoff is not None:
            handoff.note(i, written)
        moved[i], ratio[i] = tracker.update_signature(signature)
        station[i] = i if moved[i] else station[i - 1]
        if moved[i] and ring is not None:
            kept.put(i, ring)
        if save_part is not None and (i + 1 - start) % PART_FRAMES == 0 and i + 1 < n:
            a = i + 1 - PART_FRAMES
            save_part(FramePassPart(a, kept.part(a, i + 1), moved[a : i + 1], ratio[a : i + 1],
                                    station[a : i + 1], tracker.reference))
        if progress is not None:
            progress(i + 1)
    # The creep before a stroke makes the station's last frame a moving one.
    moved = promote_creep(moved, ratio, stations.creep_factor)
    station = np.where(moved, np.arange(n), 0)
    station = np.maximum.accumulate(station)
    # A frame where the rig moved whose chunk took it for stationary (a slow creep that
    # only the comparison with an earlier chunk's frame shows): its ring, decoded again.
    missing = [i for i in range(n) if moved[i] and not kept.has(i)]
    for i, ring in iter_frames(executor, RingTask(laser), dataset, frames=missing):
        kept.put(i, ring)
    for i in np.flatnonzero(~moved):
        kept.store.put(int(i), _emptied(int(kept.scanned[station[i]])))
        if handoff is not None:
            handoff.discard(int(i))
    # A stationary frame shows its station's ring: it counts that ring's samples.
    samples = kept.own[station]
    warnings = [f"frame {i}: {w}" for i in sorted(kept.notes) for w in kept.notes[i]]
    return FramePassResult(LaserResult(kept.store, warnings), moved, ratio, samples)


class _Kept:
    """The moving frames' rings as the pass finds them: on disk
    (:class:`~omnipipe.laser.store.RingStore`), with each one's sample count, scan lines
    and warnings in memory (a few bytes a frame)."""

    def __init__(self, n: int) -> None:
        self.store = RingStore(n)
        self.own = np.zeros(n, int)  # each frame's own ring's samples
        self.scanned = np.zeros(n, int)
        self.notes: dict[int, list[str]] = {}
        self._has = np.zeros(n, bool)

    def put(self, i: int, ring: LaserRing) -> None:
        self.own[i], self.scanned[i] = len(ring.pixels), ring.scanned
        if ring.warnings:
            self.notes[i] = list(ring.warnings)
        self.store.put(i, ring)
        self._has[i] = True

    def has(self, i: int) -> bool:
        return bool(self._has[i])

    def part(self, a: int, b: int) -> list[LaserRing | None]:
        """Frames a..b-1's rings (None: not found yet), read back for a checkpoint part."""
        return [self.store[i] if self._has[i] else None for i in range(a, b)]


def _restore(
    parts: Iterable[FramePassPart],
    tracker: StationTracker,
    kept: _Kept,
    moved: np.ndarray,
    ratio: np.ndarray,
    station: np.ndarray,
) -> int:
    """Fill the pass's state from ``parts``, as far as they follow each other from
    frame 0; returns the first frame still to decode."""
    start = 0
    for part in parts:
        end = start + len(part.moved)
        if part.first != start or end > len(moved) or not (
            len(part.rings) == len(part.motion_ratio) == len(part.station) == end - start
        ):
            break
        for k, ring in enumerate(part.rings):
            if ring is not None:
                kept.put(start + k, ring)
        moved[start:end], ratio[start:end] = part.moved, part.motion_ratio
        station[start:end] = part.station
        tracker.reference = part.reference
        start = end
    return start


_EMPTIED: dict[int, LaserRing] = {}


def _emptied(scanned: int) -> LaserRing:
    """A stationary frame's ring: no samples (its station's ring has them), ``scanned``
    scan lines. One shared object per ``scanned`` (nothing changes a ring once the pass
    returns it): a ring of its own cost 1 KB per stationary frame, 100 MB over
    100,000 frames."""
    if scanned not in _EMPTIED:
        _EMPTIED[scanned] = LaserRing(
            np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), scanned=scanned
        )
    return _EMPTIED[scanned]

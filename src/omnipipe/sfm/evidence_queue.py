"""The keyframe steps' scale evidence, measured in the executor's workers.

:class:`EvidenceQueue` submits each step's two scale measurements (laser template
matches, Eq. 17; feature depths on the light-section wall: :func:`omnipipe.sfm.tasks.step_evidence`)
once the flat field of the keyframes around it is known (:mod:`omnipipe.sfm.flat_field`),
at most twice the executor's parallelism in flight (each holds two images), and moves a
finished step's arrays to the run's scratch. :func:`gray_for_worker` is how a keyframe's
(H, W) grey image travels to a worker.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import Executor, Future
from dataclasses import replace

import numpy as np

from omnipipe.executor import parallelism, shares_files
from omnipipe.sfm.flat_field import FlatWindow
from omnipipe.sfm.image_store import ImageStore, StoredImage
from omnipipe.sfm.keyframe_jobs import EvidenceJob, evidence_held, finished
from omnipipe.sfm.ransac import RelativeMotion
from omnipipe.sfm.step_records import StepPair
from omnipipe.sfm.tasks import step_evidence
from omnipipe.sfm.types import SfmContext, SfmInputs, StepEvidence
from omnipipe.spill import Pack


def gray_for_worker(
    grays: ImageStore, k: int, gray: np.ndarray, executor: Executor
) -> np.ndarray | StoredImage:
    """Keyframe ``k``'s grey image ``gray`` (H, W) as sent to ``executor``'s worker: a
    reference to its file in ``grays`` (the keyframe store, ``k`` an index into it) for
    a local pool's worker when the stored copy holds the same values (an 8- or
    16-bit grey image), else the array itself (inline, a Dask cluster, a float image)."""
    exact = gray.dtype in (np.uint8, np.uint16)
    return grays.ref(k) if exact and shares_files(executor) else gray


class EvidenceQueue:
    """The keyframe steps' evidence jobs, in step order (step k: keyframes k -> k + 1),
    with the flat field's window of keyframes (``ctx.config.laser_scale``)."""

    def __init__(self, ctx: SfmContext, inputs: SfmInputs, grays: ImageStore) -> None:
        self.ctx = ctx
        self.inputs = inputs
        self.grays = grays
        self.flat = FlatWindow(
            ctx.camera, ctx.config.laser_scale.flat_field_keyframes, shares_files(ctx.executor)
        )
        self.jobs: list[EvidenceJob] = []
        # The jobs whose arrays are not in the scratch yet (indices into jobs): moved
        # there once the worker has finished (:meth:`settle`).
        self._open: list[int] = []
        self._seen = 0
        self._in_flight: deque[Future] = deque()

    def measure(
        self,
        pair: StepPair,
        motion: RelativeMotion | None,
        gray_a: np.ndarray,
        gray_b: np.ndarray,
        tracked: bool = False,
    ) -> None:
        """The step's evidence: its status, and for a translation both scale sources
        (laser Eq. 17 with its peaks, feature depths) measured in a worker; at most
        twice the executor's parallelism in flight (each holds two images). ``tracked``:
        the matches were verified frame to frame (:attr:`StepEvidence.tracked`)."""
        a, b = pair.a, pair.b
        if motion is None:
            self.jobs.append(EvidenceJob(StepEvidence.unmeasured(a, b, np.eye(4), None, "lost")))
            return
        inl = pair.matches[motion.inliers]
        b_from_a = motion.rig2_from_rig1.copy()
        if not motion.translation_reliable:
            self.ctx.warnings.append(f"frames {a}->{b}: rotation only (no measurable translation)")
            self.jobs.append(
                EvidenceJob(StepEvidence.unmeasured(a, b, b_from_a, inl, "rotation"))
            )
            return
        config, ex, k = self.ctx.config, self.ctx.executor, len(self.grays) - 2
        held_a, held_b = gray_for_worker(self.grays, k, gray_a, ex), gray_for_worker(self.grays, k + 1, gray_b, ex)
        args = (
            self.ctx.camera,
            self.inputs.rings.rings[a].points_in_rig,
            b_from_a[:3, :3],
            b_from_a[:3, 3],
            pair.features_a.rays_in_rig[inl[:, 0]],
            pair.features_b.rays_in_rig[inl[:, 1]],
            config.laser_scale,
            config.scale_check,
        )
        # Submitted once the keyframes around it give its flat field (sfm.flat_field).
        future, sent = self.flat.submit(k, lambda flat: ex.submit(step_evidence, held_a, held_b, *args, flat))
        evidence = replace(StepEvidence.unmeasured(a, b, b_from_a, inl, "ok"), tracked=tracked)
        self.jobs.append(EvidenceJob(evidence, future))
        self.throttle(sent)

    def throttle(self, sent: list[Future]) -> None:
        """At most twice the executor's parallelism of evidence jobs in flight."""
        self._in_flight.extend(sent)
        while len(self._in_flight) > 2 * parallelism(self.ctx.executor):
            self._in_flight.popleft().result()

    def add_keyframe(self, gray: np.ndarray, ring_pixels: np.ndarray) -> None:
        """The next keyframe's (H, W) grey image and its ring's (N, 2) pixels to the flat
        field's window; the steps it releases are submitted."""
        self.throttle(self.flat.add_keyframe(gray, ring_pixels))

    def finish(self) -> None:
        """Every step still waiting for its flat field submitted (the run's end)."""
        self.throttle(self.flat.finish())

    def step(self, k: int) -> StepEvidence | None:
        """Keyframe step k -> k + 1's evidence as measured so far (None: not yet)."""
        return self.jobs[k].evidence if 0 <= k < len(self.jobs) else None

    def settle(self, pack: Pack) -> None:
        """The steps' evidence whose workers have finished (or that had none): their
        arrays into ``pack`` (:func:`evidence_held`; the same values), so that what the
        loop holds in memory does not grow with the keyframes. A worker's exception is
        left in its future, raised where the result is asked for."""
        self._open += range(self._seen, len(self.jobs))
        self._seen = len(self.jobs)
        still = []
        for k in self._open:
            job = self.jobs[k]
            if job.future is None or finished(job.future):
                self.jobs[k] = EvidenceJob(evidence_held(pack, job.result()))
            else:
                still.append(k)
        self._open = still

    def held(self, pack: Pack) -> list[StepEvidence]:
        """Every step's complete evidence (waits for the workers), its arrays in ``pack``."""
        return [evidence_held(pack, job.result()) for job in self.jobs]

"""The one decoding pass and the frame-parallel motion: the same result as the serial stages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnipipe import laser, sfm
from omnipipe.camera import camera_from_rig
from omnipipe.dataset import open_dataset
from omnipipe.executor import open_executor
from omnipipe.image import gray_without_laser
from omnipipe.pipeline import frame_pass
from omnipipe.sfm.stations import StationConfig, StationTracker, promote_creep


@pytest.fixture(scope="module")
def stop_and_go(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from omnipipe.sim import make_scenario, run

    out = tmp_path_factory.mktemp("framepass") / "ds"
    run(make_scenario("bend-small", frames=18, size=(480, 360), seed=3), out, workers=1)
    return out


def test_one_pass_gives_the_serial_rings_and_stations(stop_and_go: Path) -> None:
    dataset = open_dataset(stop_and_go)
    serial = laser.run(laser.LaserConfig(), dataset.rig, (dataset.read_frame(i) for i in range(len(dataset))))
    tracker = StationTracker(camera_from_rig(dataset.rig).valid_mask())
    tested = np.array(
        [tracker.update(gray_without_laser(f, dataset.rig.laser.channel)) for f in (dataset.read_frame(i) for i in range(len(dataset)))]
    )
    # The station's last frame before a detected motion is moving too when it creeps.
    moved = promote_creep(tested[:, 0] > 0, tested[:, 1], StationConfig().creep_factor)
    assert 2 <= moved.sum() < len(dataset)  # a stop-and-go run: both kinds of frame
    for workers in (1, 2):
        done: list[int] = []
        with open_executor(workers) as ex:
            result = frame_pass.run(laser.LaserConfig(), StationConfig(), dataset, ex, done.append)
        assert np.array_equal(result.moved, moved), workers
        assert done[-1] == len(dataset)
        # A stationary frame counts its station's ring (its own is never extracted).
        station = np.maximum.accumulate(np.where(moved, np.arange(len(moved)), 0))
        own = np.array([len(r.pixels) for r in serial.rings])
        assert np.array_equal(result.ring_samples, own[station])
        for a, b, keep in zip(serial.rings, result.rings.rings, moved, strict=True):
            if keep:  # a standing robot's repeated rings are not kept
                assert np.array_equal(a.pixels, b.pixels)
                assert np.array_equal(a.points_in_rig, b.points_in_rig)
                assert a.warnings == b.warnings
            else:
                assert len(b.pixels) == 0 and not b.warnings


def test_a_creep_only_the_run_sees_gets_its_ring(
    stop_and_go: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Frames creeping a fraction of a pixel each: each looks stationary next to the
    one before it (which is all a chunk sees), but the run's tracker, comparing with
    its station's first frame, finds motion every few frames: those rings are
    extracted after the pass, and every moved frame's ring is the serial one."""
    import shutil

    import cv2

    from omnipipe.dataset import write_image

    source = open_dataset(stop_and_go)
    base = source.read_frame(0)
    creep = tmp_path / "creep"
    (creep / "frames").mkdir(parents=True)
    shutil.copy(stop_and_go / "rig.yaml", creep / "rig.yaml")
    h, w = base.shape[:2]
    for k in range(12):
        shift = np.float32([[1, 0, 0.2 * k], [0, 1, 0]])
        write_image(creep / "frames" / f"{k:06d}.png", cv2.warpAffine(base, shift, (w, h)))
    dataset = open_dataset(creep)
    tracker = StationTracker(camera_from_rig(dataset.rig).valid_mask())
    tested = np.array(
        [tracker.update(gray_without_laser(f, dataset.rig.laser.channel)) for f in (dataset.read_frame(i) for i in range(len(dataset)))]
    )
    # The station's last frame before a detected motion is moving too when it creeps.
    moved = promote_creep(tested[:, 0] > 0, tested[:, 1], StationConfig().creep_factor)
    fetched: list[int] = []
    task = frame_pass.RingTask.__call__
    monkeypatch.setattr(
        frame_pass.RingTask, "__call__", lambda self, src: fetched.extend(src.frames) or task(self, src)
    )
    with open_executor(1) as ex:  # inline: chunks of 3 frames
        result = frame_pass.run(laser.LaserConfig(), StationConfig(), dataset, ex)
    assert np.array_equal(result.moved, moved)
    assert fetched and all(moved[i] for i in fetched)
    serial = laser.run(laser.LaserConfig(), dataset.rig, (dataset.read_frame(i) for i in range(len(dataset))))
    for a, b, keep in zip(serial.rings, result.rings.rings, moved, strict=True):
        if keep:
            assert np.array_equal(a.points_in_rig, b.points_in_rig)


def test_frame_parallel_motion_equals_serial(stop_and_go: Path) -> None:
    dataset = open_dataset(stop_and_go)
    config = sfm.SfmConfig()
    with open_executor(1) as ex:
        frames = frame_pass.run(laser.LaserConfig(), StationConfig(), dataset, ex)
    serial = sfm.run(
        config, sfm.SfmInputs(dataset.rig, dataset.read_frame, len(dataset), frames.rings)
    )
    assert serial.keyframe.sum() >= 3
    with open_executor(2) as ex:
        done: list[int] = []
        parallel = sfm.run(
            config,
            sfm.SfmInputs(
                dataset.rig, dataset.read_frame, len(dataset), frames.rings,
                moved=frames.moved, dataset=dataset,
            ),
            progress=done.append,
            executor=ex,
        )
    assert done[-1] == len(dataset)
    assert np.array_equal(parallel.keyframe, serial.keyframe)
    assert np.array_equal(parallel.world_from_rig, serial.world_from_rig)
    assert parallel.warnings == serial.warnings


def test_handed_on_frames_give_the_same_motion(stop_and_go: Path, tmp_path: Path) -> None:
    """The pass leaves each moving frame for the later stages' workers (a red laser's
    colour frame planar: its green channel as decoded first), which read it from there:
    with the moving frames' files gone from the dataset after the pass, the same motion."""
    import shutil

    from omnipipe.handoff import FrameHandoff

    copy = tmp_path / "ds"
    shutil.copytree(stop_and_go, copy)
    dataset = open_dataset(copy)
    config = sfm.SfmConfig()
    with open_executor(2) as ex:
        frames = frame_pass.run(laser.LaserConfig(), StationConfig(), dataset, ex)
        plain = sfm.run(config, sfm.SfmInputs.of_dataset(dataset, frames.rings, frames.moved), executor=ex)
    with open_executor(2) as ex, FrameHandoff(len(dataset)) as handoff:
        handed = frame_pass.run(laser.LaserConfig(), StationConfig(), dataset, ex, handoff=handoff)
        left = sorted(int(p.stem) for p in Path(handoff.folder).glob("*.npy"))
        assert left == np.flatnonzero(handed.moved).tolist()  # stationary frames' removed
        for i in left:  # its grey channel as decoded; then not readable from the dataset
            decoded = dataset.read_frame(i)
            first = np.load(Path(handoff.folder) / f"{i:07d}.npy", mmap_mode="r")
            assert np.array_equal(first, decoded[..., 1] if dataset.rig.laser.channel == "red" else decoded)
            dataset.frame_paths[i].write_bytes(b"")
        inputs = sfm.SfmInputs.of_dataset(dataset, handed.rings, handed.moved)
        inputs.handoff = handoff.folder
        motion = sfm.run(config, inputs, executor=ex)
    assert not Path(handoff.folder).exists()
    assert np.array_equal(handed.moved, frames.moved)
    assert np.array_equal(motion.keyframe, plain.keyframe)
    assert np.array_equal(motion.world_from_rig, plain.world_from_rig)
    assert motion.warnings == plain.warnings

"""A keyframe step's relative motion trusted or not: one decision, with or without sensors."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from omnipipe.sfm import motion_trust
from omnipipe.sfm.motion_trust import DIRECTION_MIN_INLIERS, MOTION_MIN_INLIERS, untrusted_motions
from omnipipe.sfm.step_decide import decide_step
from omnipipe.sfm.step_records import Followed
from omnipipe.sfm.types import Keyframes, StepEvidence


def _followed(inliers: list[int]) -> Followed:
    """Keyframes 0, 10, 20, ... whose steps have ``inliers`` RANSAC inliers each (and as
    many feature matches less two), every step measured ("ok")."""
    rng = np.random.default_rng(0)
    frames = [10 * k for k in range(len(inliers) + 1)]
    evidence = []
    for k, n in enumerate(inliers):
        t = rng.normal(size=3)
        b_from_a = np.eye(4)
        b_from_a[:3, 3] = t / np.linalg.norm(t)
        m = np.stack([np.arange(n), np.arange(n)], axis=1)
        evidence.append(
            StepEvidence(frames[k], frames[k + 1], b_from_a, m, None, np.zeros(n), 12.0, n - 2, "ok")
        )
    n_frames = frames[-1] + 1
    return Followed(
        Keyframes(frames, [], None, [], evidence),  # type: ignore[arg-type]
        [],
        {},
        np.ones(n_frames, bool),
        np.isin(np.arange(n_frames), frames),
        np.zeros(n_frames, bool),
        np.zeros(n_frames, bool),
    )


def _texture(monkeypatch: pytest.MonkeyPatch, value: float) -> list[int]:
    """The run's wall texture set to ``value``; the returned list counts its readings."""
    reads: list[int] = []

    def texture(config, inputs) -> float:
        reads.append(1)
        return value

    monkeypatch.setattr(motion_trust, "run_texture", texture)
    return reads


def _ctx() -> SimpleNamespace:
    return SimpleNamespace(config=None, warnings=[])


@pytest.mark.parametrize("odometry", [None, "the robot's odometry"])
def test_few_inliers_on_a_plain_wall_are_lost_with_or_without_sensors(
    monkeypatch: pytest.MonkeyPatch, odometry
) -> None:
    """Random-wide seed 25 (smooth, local contrast 0.32): steps of 46 / 21 / 46 inliers,
    their directions 0.7-10 deg off; seed 29 (0.28): 124-276 inliers, kept, its direction
    stated to 2 deg (0.3-1.7 deg off). The decision does not look at the sensors."""
    _texture(monkeypatch, 0.32)
    followed = _followed([46, 150, 21])
    ctx = _ctx()
    untrusted_motions(ctx, SimpleNamespace(odometry=odometry), followed)  # type: ignore[arg-type]
    ev = followed.keyframes.evidence
    assert [e.status for e in ev] == ["lost", "ok", "lost"]
    assert followed.lost.tolist() == [i in (10, 30) for i in range(31)]
    lost = ev[0]
    assert lost.inliers is None and lost.laser is None and math.isnan(lost.feature_scale_mm)
    assert lost.feature_matches == 44  # the report's "at most N feature matches" still reads it
    assert "46 matches" in lost.lost_reason and "0.32" in lost.lost_reason
    assert len(ctx.warnings) == 3 and ctx.warnings[0].startswith("frames 0->10: relative motion not trusted")
    assert ctx.warnings[1].startswith("frames 10->20: the step's direction rests on 150 matches")
    assert "+-2 deg" in ctx.warnings[1] and "3.5 % of the step's length" in ctx.warnings[1]
    # Decided as a step without relative motion, its reason saying why.
    step = decide_step(SimpleNamespace(config=None), followed.keyframes, 0, 0.0)  # type: ignore[arg-type]
    assert step.check.confidence == "none" and step.check.reason == lost.lost_reason
    assert step.check.feature_matches == 44 and not step.check.reliable


def test_a_textured_wall_or_enough_inliers_keep_the_vision(monkeypatch: pytest.MonkeyPatch) -> None:
    """A wall at or above the floor keeps every step (random-wide seed 31, joints at 0.82:
    60-86 inliers, 0.3-1.2 deg) and says nothing; a run whose every step has
    DIRECTION_MIN_INLIERS reads no frame for its texture; one whose step has the lost
    bar's inliers keeps it, its direction stated."""
    reads = _texture(monkeypatch, 0.82)
    followed = _followed([60, 86])
    ctx = _ctx()
    untrusted_motions(ctx, SimpleNamespace(), followed)  # type: ignore[arg-type]
    assert [e.status for e in followed.keyframes.evidence] == ["ok", "ok"] and not followed.lost.any()
    assert reads == [1] and ctx.warnings == []
    reads = _texture(monkeypatch, 0.2)
    followed = _followed([DIRECTION_MIN_INLIERS, 400])
    ctx = _ctx()
    untrusted_motions(ctx, SimpleNamespace(), followed)  # type: ignore[arg-type]
    assert [e.status for e in followed.keyframes.evidence] == ["ok", "ok"] and reads == [] and ctx.warnings == []
    followed = _followed([MOTION_MIN_INLIERS, 400])
    ctx = _ctx()
    untrusted_motions(ctx, SimpleNamespace(), followed)  # type: ignore[arg-type]
    assert [e.status for e in followed.keyframes.evidence] == ["ok", "ok"] and reads == [1]
    assert len(ctx.warnings) == 1 and "rests on 100 matches" in ctx.warnings[0]

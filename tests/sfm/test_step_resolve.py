"""A flagged step resolved by its prior (sfm.step_resolve.resolve_by_prior): which length
it takes, with the laser's re-match around it stubbed (a seeded fake of Eq. 17's)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from omnipipe.sfm import step_decide, step_resolve
from omnipipe.sfm.laser_scale import LaserMatches
from omnipipe.sfm.scale_check import StepCheck
from omnipipe.sfm.step_decide import DecidedStep, RunScale
from omnipipe.sfm.types import SfmConfig


def _flagged(feature_mm: float) -> DecidedStep:
    """A step whose laser peaks are all near zero (the template match could not see it)
    and whose feature depths measured ``feature_mm``."""
    check = StepCheck(19, 31, 9.0, 0.999, feature_mm, 754, math.nan, "none",
                      "ambiguous laser scale", (1.06, 0.48, 0.64))
    return DecidedStep(np.eye(4), math.nan, None, None, check)


@pytest.mark.parametrize(("rematched", "want"), [(15.2, 17.03), (17.2, 17.2)])
def test_a_laser_rematch_counts_only_where_the_prior_confirms_it(monkeypatch, rematched: float, want: float) -> None:
    """Random-wide seed 3s: feature depths 17.03 mm and the odometry 17.0 +- 0.4 agree
    (true 17.37); the laser re-matched around them at the search window's edge, 15.2,
    used to replace them. Now a re-match outside 2 sigma of the prior is dropped (the
    step keeps the confirmed candidate, no laser anchors); one inside is taken."""
    lm = LaserMatches(np.arange(3), np.full(3, rematched), np.zeros((3, 2)), np.ones(3), rematched)
    monkeypatch.setattr(step_decide, "laser_around", lambda ctx, kf, k, length: lm)
    monkeypatch.setattr(step_resolve, "bridge_estimate", lambda *a, **k: (17.0, 0.4, "odometry"))
    ctx = SimpleNamespace(config=SfmConfig(), warnings=[])
    kf = SimpleNamespace(evidence=[SimpleNamespace(a=19, b=31, status="ok", inliers=None, log_scales=np.zeros(0))])
    decided, lengths = [_flagged(17.03)], np.array([math.nan])
    step_resolve.resolve_by_prior(ctx, kf, decided, lengths, None, RunScale(0.0, False))
    assert decided[0].check.confidence == "resolved"
    assert lengths[0] == pytest.approx(want) and decided[0].scale_mm == pytest.approx(want)
    assert (decided[0].laser is None) == (rematched == 15.2)

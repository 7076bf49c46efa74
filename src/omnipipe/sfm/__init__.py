"""Camera-motion stage (paper Sec. V): stationary frames, two-view geometry on rays
(eight-point, RANSAC), metric scale from the laser (Eq. 17), bundle adjustment.

``run(config, inputs) -> SfmResult`` (:mod:`omnipipe.sfm.pipeline`) reads as the paper's
steps; the steps live in :mod:`~omnipipe.sfm.keyframes` (the frame loop),
:mod:`~omnipipe.sfm.step_scale` (each step's length and the run's scale) and
:mod:`~omnipipe.sfm.adjust` (bundle adjustment, resection); what they hand each other is
in :mod:`~omnipipe.sfm.types`.
"""

from omnipipe.sfm.pipeline import run
from omnipipe.sfm.scale_check import StepCheck, UnreliableStretch
from omnipipe.sfm.step_scale import combine_scales
from omnipipe.sfm.types import SfmConfig, SfmInputs, SfmResult

__all__ = [
    "SfmConfig",
    "SfmInputs",
    "SfmResult",
    "StepCheck",
    "UnreliableStretch",
    "combine_scales",
    "run",
]

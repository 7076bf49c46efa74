"""Evaluation stage: a reconstruction against a dataset's ground truth.

The stage is :func:`omnipipe.evaluation.stage.run`; trajectory errors:
:mod:`.trajectory`; the command: :mod:`.cli`.
"""

from omnipipe.evaluation.stage import (
    DefectMatch,
    EvaluationConfig,
    EvaluationInputs,
    EvaluationResult,
    read_points_ply,
    run,
)

__all__ = [
    "DefectMatch",
    "EvaluationConfig",
    "EvaluationInputs",
    "EvaluationResult",
    "read_points_ply",
    "run",
]

"""The reconstruction pipeline: dataset in, contract outputs out.

The run and the writing of its outputs: :mod:`.reconstruct`; the decoding pass:
:mod:`.frame_pass`; what the user is told about the camera motion: :mod:`.quality`;
batches: :mod:`.batch`; the command line: :mod:`.cli`.
"""

from omnipipe.pipeline.reconstruct import (
    ProgressFactory,
    Reconstruction,
    report_inputs,
    run,
    table_one,
    write,
)
from omnipipe.pipeline.run_config import ReconstructConfig

__all__ = [
    "ProgressFactory",
    "ReconstructConfig",
    "Reconstruction",
    "report_inputs",
    "run",
    "table_one",
    "write",
]

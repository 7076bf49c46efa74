"""The reconstruction pipeline: dataset in, contract outputs out.

The run: :mod:`.reconstruct` (its settings and log: :mod:`.run_config`; each stage's
call: :mod:`.stage_calls`; their sequence and checkpoints: :mod:`.run_state`; report.json's
content: :mod:`.summary`); the writing of its outputs: :mod:`.outputs`; the decoding pass:
:mod:`.frame_pass`; what the user is told about the camera motion: :mod:`.quality`;
batches: :mod:`.batch`; the command line: :mod:`.cli`.
"""

from omnipipe.pipeline.outputs import report_inputs, table_one, write
from omnipipe.pipeline.reconstruct import Reconstruction, run
from omnipipe.pipeline.run_config import ReconstructConfig
from omnipipe.progress import ProgressFactory

__all__ = [
    "ProgressFactory",
    "ReconstructConfig",
    "Reconstruction",
    "report_inputs",
    "run",
    "table_one",
    "write",
]

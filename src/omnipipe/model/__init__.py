"""Model stage (paper Sec. VI): integrated wall points, mesh, texture, model files.

The stage is :func:`omnipipe.model.stage.run`; the modules: :mod:`.stage`,
:mod:`.texture`, :mod:`.flips`, :mod:`.export`.
"""

from omnipipe.model.export import write_glb, write_obj, write_outputs, write_ply
from omnipipe.model.stage import (
    ModelConfig,
    ModelInputs,
    ModelResult,
    integrate,
    mesh_unrolled,
    orient_towards_axis,
    run,
    textured_mesh,
)

__all__ = [
    "ModelConfig",
    "ModelInputs",
    "ModelResult",
    "integrate",
    "mesh_unrolled",
    "orient_towards_axis",
    "run",
    "textured_mesh",
    "write_glb",
    "write_obj",
    "write_outputs",
    "write_ply",
]

"""Model stage (paper Sec. VI): integrated wall points, mesh, texture, model files.

The stage is :func:`omnipipe.model.stage.run`; the modules: :mod:`.mesh`,
:mod:`.texture`, :mod:`.flips`, :mod:`.export`.
"""

from omnipipe.model.export import write_glb, write_obj, write_outputs, write_ply
from omnipipe.model.mesh import integrate, mesh_unrolled, orient_towards_axis, textured_mesh
from omnipipe.model.stage import ModelConfig, ModelInputs, ModelResult, run

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

"""omnipipe: measured, textured 3-D pipe models from an omni-directional rangefinder.

Stages (one subpackage each): ``camera`` (hyperboloid model, perspective views),
``laser`` (light section), ``baseline`` (baseline optimisation), ``sfm`` (camera
motion), ``model`` (integration, mesh, texture), ``analysis`` (diameter, defects),
``sim`` (simulator), ``report`` and ``cli``.
"""

from omnipipe.errors import OmnipipeError

__version__ = "0.1.0"
__all__ = ["OmnipipeError", "__version__"]

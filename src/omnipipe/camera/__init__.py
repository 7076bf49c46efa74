"""Camera stage: the hyperboloid-mirror camera model (Eq. 1-3) and perspective views (Fig. 11)."""

from omnipipe.camera.hyperboloid import OmniCamera
from omnipipe.camera.perspective import PerspectiveView

__all__ = ["OmniCamera", "PerspectiveView"]

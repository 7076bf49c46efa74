"""Camera stage: camera models behind one interface (hyperboloid Eq. 1-3, unified, ocam),
``camera_from_rig`` and perspective views (Fig. 11)."""

from omnipipe.camera.base import CameraModel
from omnipipe.camera.factory import camera_from_parts, camera_from_rig
from omnipipe.camera.hyperboloid import OmniCamera
from omnipipe.camera.ocam import OcamCamera
from omnipipe.camera.perspective import PerspectiveView
from omnipipe.camera.unified import UnifiedCamera

__all__ = [
    "CameraModel",
    "OcamCamera",
    "OmniCamera",
    "PerspectiveView",
    "UnifiedCamera",
    "camera_from_parts",
    "camera_from_rig",
]

"""``camera_from_rig``: the one place where a rig's camera model is built."""

from __future__ import annotations

from omnipipe.camera.base import CameraModel
from omnipipe.camera.hyperboloid import OmniCamera
from omnipipe.camera.ocam import OcamCamera
from omnipipe.camera.unified import UnifiedCamera
from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, Mirror, OcamParams, Rig, UnifiedParams


def camera_from_parts(
    intrinsics: CameraIntrinsics,
    mirror: Mirror | None,
    model: UnifiedParams | OcamParams | None,
) -> CameraModel:
    """The camera of ``model`` (None: the hyperboloid of ``mirror``, Eq. 1-3).

    Raises:
        ConfigError: a hyperboloid camera without a mirror.
    """
    if isinstance(model, UnifiedParams):
        return UnifiedCamera(intrinsics, model)
    if isinstance(model, OcamParams):
        return OcamCamera(intrinsics, model)
    if mirror is None:
        raise ConfigError("mirror", "the hyperboloid camera model needs the mirror section")
    return OmniCamera(intrinsics, mirror)


def camera_from_rig(rig: Rig) -> CameraModel:
    """The camera of ``rig``, whatever its ``camera.model``: every stage uses this."""
    return camera_from_parts(rig.camera, rig.mirror, rig.model)

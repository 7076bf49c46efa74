"""The best camera view of each defect: a perspective crop of an omni frame.

For a defect the wall point nearest its centre (axial position, angle) is taken from the
measured points; among the registered frames whose camera sees it (``CameraModel.project``
valid) the one whose mirror focus is closest to it shows it largest. A pinhole view from
that focus towards the point (:class:`omnipipe.camera.perspective.PerspectiveView`, the
paper's Fig. 11, sampled through the camera model's ``project``) is drawn with the
defect's half-height extent outlined (the wall taken as a cylinder about the frame's z
axis through the wall point's distance from it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.spill import drop_pages

if TYPE_CHECKING:
    from omnipipe.camera.base import CameraModel
    from omnipipe.contract import Defect
    from omnipipe.report.relief import WallPoints

VIEW_PX = 320
"""Side of a camera view (px)."""


@dataclass(frozen=True)
class DefectView:
    """A defect's camera view.

    Attributes:
        frame: 0-based frame index (frames/ order) it was cut from.
        image: (VIEW_PX, VIEW_PX, 3) uint8, contrast-stretched, the defect outlined in yellow.
    """

    frame: int
    image: np.ndarray


def centre_point(d: Defect, wall: WallPoints, points_in_world: np.ndarray) -> np.ndarray | None:
    """(3,) world position (mm) of the measured wall point nearest the defect's centre."""
    return nearest_wall_point(d.axial_centre_mm, d.angle_deg, wall, points_in_world)


def nearest_wall_point(
    axial_mm: float,
    angle_deg: float,
    wall: WallPoints,
    points_in_world: np.ndarray,
    on_wall_mm: float | None = None,
) -> np.ndarray | None:
    """(3,) world position (mm) of the measured wall point nearest (axial, omnipipe angle)
    on the unrolled wall, or None without points. ``on_wall_mm``: only points within this
    of the fitted wall (not the branch seen through a lateral's opening)."""
    if len(points_in_world) != len(wall.axial_mm) or not len(points_in_world):
        return None
    # A chunk of points at a time (the distances' temporaries a chunk's, not the run's):
    # the first nearest point, as np.argmin over them all (a NaN distance wins, as there).
    best, k, finite = np.inf, 0, False
    for a in range(0, len(points_in_world), _POINTS_AT_ONCE):
        part = slice(a, a + _POINTS_AT_ONCE)
        du = ((wall.angle_deg[part] - angle_deg + 180.0) % 360.0 - 180.0) * math.pi / 180.0 * wall.radius_mm
        dz = wall.axial_mm[part] - axial_mm
        d2 = du * du + dz * dz
        if on_wall_mm is not None:
            d2 = np.where(np.abs(wall.deviation_mm[part]) <= on_wall_mm, d2, np.inf)
            finite = finite or bool(np.isfinite(d2).any())
        i = int(np.argmin(d2))
        if np.isnan(d2[i]):
            k = a + i
            break
        if d2[i] < best or a == 0:
            best, k = float(d2[i]), a + i
        drop_pages()  # this chunk's points read (omnipipe.spill): a chunk's pages resident
    if on_wall_mm is not None and not finite:
        return None
    return np.asarray(points_in_world[k], float)


_POINTS_AT_ONCE = 1 << 16
"""Wall points :func:`nearest_wall_point` measures at a time."""


def best_frame(
    point_world: np.ndarray, world_from_rig: np.ndarray, camera: CameraModel
) -> tuple[int, np.ndarray] | None:
    """(index into ``world_from_rig``, the point in that rig frame) of the pose closest to
    the point that sees it, or None."""
    rig_from_world = np.linalg.inv(world_from_rig)
    p = np.einsum("nij,j->ni", rig_from_world[:, :3, :3], point_world) + rig_from_world[:, :3, 3]
    _, valid = camera.project(p)
    if not valid.any():
        return None
    dist = np.where(valid, np.linalg.norm(p, axis=1), np.inf)
    k = int(np.argmin(dist))
    return k, p[k]


def _outline_rig(d: Defect, p: np.ndarray) -> np.ndarray:
    """(M, 3) rig-frame points of the defect's half-height extent around ``p``."""
    z = np.array([0.0, 0.0, 1.0])
    along = float(p @ z)
    radial = p - along * z
    radius = float(np.linalg.norm(radial))
    e1 = radial / max(radius, 1e-9)
    e2 = np.cross(z, e1)
    half_phi = 0.5 * d.width_mm / max(radius, 1e-9)
    half_len = 0.5 * d.length_mm
    phis = np.linspace(-half_phi, half_phi, 12)
    edge = [(phi, -half_len) for phi in phis] + [(phi, half_len) for phi in phis[::-1]]
    return np.array(
        [radius * (math.cos(phi) * e1 + math.sin(phi) * e2) + (along + v) * z for phi, v in edge]
    )


def camera_view(image: np.ndarray, camera: CameraModel, d: Defect, p: np.ndarray) -> np.ndarray:
    """The perspective crop of ``image`` towards rig point ``p`` covering the defect with
    a margin, its outline drawn, as (VIEW_PX, VIEW_PX, 3) uint8."""
    import cv2

    from omnipipe.camera.perspective import PerspectiveView

    size = max(d.width_mm, d.length_mm, 10.0) * 1.6 + 20.0
    focal = VIEW_PX * float(np.linalg.norm(p)) / size
    view = PerspectiveView.looking_at(p, width=VIEW_PX, height=VIEW_PX, focal_px=focal)
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    out, _ = view.render(img, camera)  # type: ignore[arg-type]
    out = np.ascontiguousarray(out[:, :, :3]).astype(np.float32)
    # Contrast stretched to the view's 1st-99th percentile (LED light falls off fast).
    lo, hi = np.percentile(out, (1, 99))
    out = np.clip((out - lo) * (255.0 / max(float(hi - lo), 1.0)), 0, 255).astype(np.uint8)
    pts = _outline_rig(d, p)
    px, front = view.pixels_of_rays(pts / np.linalg.norm(pts, axis=1, keepdims=True))
    if front.all() and np.isfinite(px).all():
        poly = np.round(px).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [poly], True, (255, 220, 0), 1, cv2.LINE_AA)
    return out


def defect_views(
    defects: Sequence[Defect],
    wall: WallPoints | None,
    points_in_world: np.ndarray,
    world_from_rig: np.ndarray,
    frame_index: np.ndarray,
    camera: CameraModel,
    read_frame: Callable[[int], np.ndarray],
) -> list[DefectView | None]:
    """Each defect's camera view (None where no frame sees it or no wall point is near).

    Args:
        world_from_rig: (K, 4, 4) registered poses; ``frame_index`` (K,) their frames.
        read_frame: frame index -> (H, W[, C]) image.
    """
    out: list[DefectView | None] = []
    for d in defects:
        centre = None if wall is None else centre_point(d, wall, points_in_world)
        best = None if centre is None else best_frame(centre, world_from_rig, camera)
        if best is None:
            out.append(None)
            continue
        k, p = best
        frame = int(frame_index[k])
        out.append(DefectView(frame, camera_view(read_frame(frame), camera, d, p)))
    return out

"""Model stage (paper Sec. VI): integrated wall points, mesh, colours, PLY files.

Integration: every frame's metric ring points go into the world frame with the
frame's pose. Colour: the LED-lit image a few pixels off the ring along the radial
direction (at the ring itself the laser dominates the red channel).

Mesh: a Delaunay triangulation in the unrolled parameterisation of the pipe
(arc length around the axis, distance along it). The wall is a tube, a developable
surface: a 2-D Delaunay on its unrolling gives the wall's own topology, never a
triangle across the pipe, which a 3-D Delaunay of a hollow cylinder would produce
everywhere (its tetrahedra fill the inside). The angle wraps around: a margin of
points is duplicated past 2 pi and each triangle is kept once. Triangles with an
edge much longer than the spacing of the rings are dropped: holes stay holes.

Not yet here: the triangle optimisation of [25] and texture mapping / the textured
GLB and the unrolled wall image (see the project's issue tracker).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import Delaunay

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply
from omnipipe.rig import Rig


@dataclass(frozen=True)
class ModelConfig:
    """Model settings.

    Attributes:
        mesher: "unrolled-delaunay" (the only one so far).
        colour_offset_px: radial offset of the colour sample from the laser ring (px).
        max_edge_factor: drop triangles whose longest edge exceeds this many times the
            median longest edge (about one ring spacing).
    """

    mesher: str = "unrolled-delaunay"
    colour_offset_px: float = 4.0
    max_edge_factor: float = 2.0


@dataclass
class ModelInputs:
    """Per registered frame: pose, ring points and pixels, and the image."""

    camera_rig: Rig
    world_from_rig: np.ndarray
    ring_points_in_rig: list[np.ndarray]
    ring_pixels: list[np.ndarray]
    read_frame: Callable[[int], np.ndarray]


@dataclass
class ModelResult:
    """The integrated model.

    Attributes:
        points_in_world: (N, 3) mm.
        colours: (N, 3) uint8 RGB.
        point_frame: (N,) registered-frame index of each point.
        mesh_vertices: (N, 3) = points_in_world; mesh_faces: (F, 3).
        mesh_uvs, texture, unrolled, unrolled_extent: None until texture mapping exists.
    """

    points_in_world: np.ndarray
    colours: np.ndarray
    point_frame: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    mesh_uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    unrolled: np.ndarray | None = None
    unrolled_extent: tuple[float, float, float, float] | None = None


def unrolled_coordinates(
    points_in_world: np.ndarray, world_from_rig: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(angle_rad, axial_mm) of points around the path of the rig origins.

    The axis is the path's principal direction (straight pipes) with the angle
    measured from the first rig frame's x axis towards y.
    """
    origins = world_from_rig[:, :3, 3]
    axis = world_from_rig[0, :3, 2]
    if len(origins) > 2 and np.linalg.norm(origins[-1] - origins[0]) > 1.0:
        _, _, vt = np.linalg.svd(origins - origins.mean(axis=0))
        axis = vt[0] * np.sign(vt[0] @ (origins[-1] - origins[0]))
    x0 = world_from_rig[0, :3, 0] - (world_from_rig[0, :3, 0] @ axis) * axis
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(axis, x0)
    centre = origins.mean(axis=0)
    rel = points_in_world - centre
    axial = rel @ axis + (centre - origins[0]) @ axis
    angle = np.arctan2(rel @ y0, rel @ x0)
    return angle, axial


def mesh_unrolled(
    points_in_world: np.ndarray, world_from_rig: np.ndarray, max_edge_factor: float
) -> np.ndarray:
    """(F, 3) triangles of an unrolled Delaunay over the points (see module docstring)."""
    n = len(points_in_world)
    if n < 3:
        return np.zeros((0, 3), int)
    angle, axial = unrolled_coordinates(points_in_world, world_from_rig)
    radius = float(
        np.median(np.linalg.norm(points_in_world - world_from_rig[:, :3, 3].mean(axis=0), axis=1))
    )
    u = angle * radius
    margin = 0.1 * 2 * math.pi * radius
    circ = 2 * math.pi * radius
    wrap = np.flatnonzero(u < -math.pi * radius + margin)
    uu = np.concatenate([u, u[wrap] + circ])
    vv = np.concatenate([axial, axial[wrap]])
    ids = np.concatenate([np.arange(n), wrap])
    tri = Delaunay(np.stack([uu, vv], axis=1)).simplices
    # Keep each triangle once: those whose centroid lies in the main period.
    cu = uu[tri].mean(axis=1)
    tri = tri[(cu >= -math.pi * radius) & (cu < math.pi * radius)]
    faces = ids[tri]
    faces = faces[
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    ]
    p = points_in_world[faces]
    edges = np.stack(
        [np.linalg.norm(p[:, i] - p[:, (i + 1) % 3], axis=1) for i in range(3)], axis=1
    )
    # A typical triangle's longest edge spans one ring spacing; much longer ones bridge gaps.
    longest = edges.max(axis=1)
    return faces[longest <= max_edge_factor * float(np.median(longest))]


def run(
    config: ModelConfig, inputs: ModelInputs, progress: Callable[[int], None] | None = None
) -> ModelResult:
    """Integrate the rings, colour them and mesh the wall."""
    camera = OmniCamera.from_rig(inputs.camera_rig)
    pts, cols, frame = [], [], []
    centre = np.array([camera.cx, camera.cy])
    for k, (T, ring_pts, ring_px) in enumerate(
        zip(inputs.world_from_rig, inputs.ring_points_in_rig, inputs.ring_pixels, strict=True)
    ):
        if len(ring_pts):
            img = inputs.read_frame(k)
            radial = ring_px - centre
            radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
            sample = np.round(ring_px + config.colour_offset_px * radial).astype(int)
            sample[:, 0] = sample[:, 0].clip(0, camera.width - 1)
            sample[:, 1] = sample[:, 1].clip(0, camera.height - 1)
            c = img[sample[:, 1], sample[:, 0]]
            if c.ndim == 1:
                c = np.repeat(c[:, None], 3, axis=1)
            if c.dtype == np.uint16:
                c = (c // 257).astype(np.uint8)
            pts.append(apply(T, ring_pts))
            cols.append(c.astype(np.uint8))
            frame.append(np.full(len(ring_pts), k))
        if progress:
            progress(k + 1)
    if not pts:
        empty = np.zeros((0, 3))
        return ModelResult(
            empty, np.zeros((0, 3), np.uint8), np.zeros(0, int), empty, np.zeros((0, 3), int)
        )
    points = np.concatenate(pts)
    faces = mesh_unrolled(points, inputs.world_from_rig, config.max_edge_factor)
    return ModelResult(points, np.concatenate(cols), np.concatenate(frame), points, faces)


def write_ply(
    path: Path, vertices: np.ndarray, colours: np.ndarray | None, faces: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY: x y z float, red green blue uchar, optional triangles."""
    n = len(vertices)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {n}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if colours is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colours is not None:
        fields += [("r", "u1"), ("g", "u1"), ("b", "u1")]
    rec = np.zeros(n, dtype=fields)
    rec["x"], rec["y"], rec["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    if colours is not None:
        rec["r"], rec["g"], rec["b"] = colours[:, 0], colours[:, 1], colours[:, 2]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
        if faces is not None and len(faces):
            frec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            frec["n"] = 3
            frec["i"] = faces
            fh.write(frec.tobytes())


def write_outputs(result: ModelResult, out_dir: Path) -> None:
    """points.ply and mesh.ply (vertex colours) into ``out_dir``."""
    out_dir = Path(out_dir)
    write_ply(out_dir / "points.ply", result.points_in_world, result.colours)
    write_ply(out_dir / "mesh.ply", result.mesh_vertices, result.colours, result.mesh_faces)

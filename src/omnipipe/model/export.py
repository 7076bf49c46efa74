"""Model files, each in its format's own unit and axis convention.

The measurement files keep the data contract's frame and unit; the files meant for
viewers and survey tools use the unit their readers assume:

| file | unit | axes |
|---|---|---|
| ``points.ply``, ``mesh.ply`` | mm (header ``comment unit mm``) | world |
| ``points.laz`` | metre, 0.01 mm resolution (LAS 1.4, WKT local CRS in metres) | world |
| ``points.e57`` | metre (the E57 standard's unit; root ``omnipipe:unit`` "metre") | world |
| ``model.glb`` | metre (glTF's unit) | glTF, y up (:data:`GLTF_FROM_WORLD`) |
| ``model.obj`` (+ ``.mtl``, ``model_texture.png``) | metre (comment line) | as the GLB |

World frame: the rig frame of the first registered frame (DATA_CONTRACT section 4;
z along the pipe in the direction of travel, x along image columns, y along image
rows). The viewer models are turned by the proper rotation :data:`GLTF_FROM_WORLD`
(no mirroring): glTF +x = world +z (the pipe runs left to right in a viewer's default
front view, distance from the start increasing to the right), glTF +y (up) = world -y
(image rows run downwards, so "up" is the image's up), glTF +z (towards the viewer) =
world +x. The wall's triangles are wound so their normals point towards the pipe axis
(inspectors look from inside) and the GLB material is double-sided as well.
"""

from __future__ import annotations

import functools
import hashlib
import json
import shutil
import struct
import uuid
from collections.abc import Callable, Iterator
from contextlib import nullcontext
from dataclasses import dataclass
from itertools import count
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, BinaryIO, TextIO
from unittest import mock

import numpy as np

from omnipipe.errors import OutputError

if TYPE_CHECKING:
    from omnipipe.model.stage import ModelResult

#: Millimetres to metres.
M_PER_MM = 1e-3

#: (3, 3) rotation gltf_from_world (det +1): glTF x = world z, y = -world y, z = world x.
GLTF_FROM_WORLD = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])

#: Frame statement written into the files that can hold text.
FRAME_NOTE = "world = first registered rig frame (DATA_CONTRACT section 4)"

#: LAS coordinate resolution: 1e-5 m = 0.01 mm.
LAS_SCALE_M = 1e-5

#: WKT of the LAS file's local (engineering) coordinate system: the world frame in metres.
LAS_WKT = (
    'LOCAL_CS["omnipipe world frame: first registered rig frame, metre",'
    'LOCAL_DATUM["omnipipe rig frame of the first registered frame",0],'
    'UNIT["metre",1],AXIS["X",OTHER],AXIS["Y",OTHER],AXIS["Z",OTHER]]'
)

#: Texture image of model.obj (beside it; referenced by model.mtl).
OBJ_TEXTURE = "model_texture.png"

#: E57 extension (prefix, URI) holding omnipipe's root fields ``unit`` and ``frame``.
E57_EXTENSION = ("omnipipe", "https://github.com/omnipipe/omnipipe/e57/1.0")

#: Each model file's unit, axes and where the file itself states its unit.
FILE_UNITS: dict[str, dict[str, str]] = {
    "points.ply": {"unit": "mm", "axes": "world", "stated": "PLY header 'comment unit mm'"},
    "mesh.ply": {"unit": "mm", "axes": "world", "stated": "PLY header 'comment unit mm'"},
    "points.laz": {"unit": "m", "axes": "world",
                   "stated": "LAS WKT VLR UNIT[\"metre\",1], system identifier"},
    "points.e57": {"unit": "m", "axes": "world",
                   "stated": "E57 (always metres), root omnipipe:unit 'metre'"},
    "model.glb": {"unit": "m", "axes": "glTF y up (x = world z, y = -world y, z = world x)",
                  "stated": "glTF asset.extras.unit 'metre'"},
    "model.obj": {"unit": "m", "axes": "as model.glb", "stated": "comment line '# unit: metre'"},
}


def model_files(result: ModelResult) -> dict[str, dict[str, str]]:
    """The 3-D files :func:`write_outputs` writes for ``result``, each with its
    :data:`FILE_UNITS` entry (report.json ``files``)."""
    names = ["points.ply", "mesh.ply", "points.laz"]
    if len(result.points_in_world):
        names.append("points.e57")
    if result.texture is not None and result.textured_faces is not None and len(result.textured_faces):
        names += ["model.glb", "model.obj"]
    return {name: dict(FILE_UNITS[name]) for name in names}


def gltf_from_world_mm(points_mm: np.ndarray) -> np.ndarray:
    """(N, 3) world points in mm -> (N, 3) glTF/OBJ viewer coordinates in metres."""
    return (np.asarray(points_mm, float) @ GLTF_FROM_WORLD.T) * M_PER_MM


def _fail(path: Path, exc: OSError) -> OutputError:
    return OutputError(f"{path}: cannot write ({exc.strerror or exc})")


WRITE_CHUNK = 100_000
"""Points (or faces) a writer converts and writes at once: its copies are a chunk's,
not the model's (the files the same, byte for byte, whatever the chunk)."""

E57_CHUNK = 1_000_000
"""Points the E57 writer hands libE57 at once (its buffers: 27 bytes a point). Up to
this many points the file is pye57's own, byte for byte; a larger cloud is written in
chunks whose packets may fall elsewhere than in one call (the same points and values;
libE57 packs each call's points, so the bytes depend on the chunk: 65536 and 999 gave
other files than one call, 100,000 the same)."""


NORMALS_CHUNK = 1 << 14
"""Faces whose normals and corner angles :func:`_vertex_normals` computes at once (about
400 bytes a face in its float64 temporaries)."""


def _chunks(n: int, size: int | None = None) -> Iterator[tuple[int, int]]:
    """``(a, b)``: consecutive slices of ``range(n)``, ``size`` (default
    :data:`WRITE_CHUNK`) long, the last fewer. After each slice is used the scratch's
    pages are dropped (:func:`omnipipe.spill.drop_pages`): the model's arrays are mapped
    files there, and a writer reads them faster than the run's dropping thread unmaps
    them."""
    from omnipipe.spill import drop_pages

    size = size or WRITE_CHUNK
    for a in range(0, n, size):
        yield a, min(a + size, n)
        drop_pages()


def _extent(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3,) lowest and highest coordinate of the (N >= 1, 3) ``points``, a chunk at a time."""
    spans = [(points[a:b].min(axis=0), points[a:b].max(axis=0)) for a, b in _chunks(len(points))]
    return np.min([s[0] for s in spans], axis=0), np.max([s[1] for s in spans], axis=0)


def write_ply(
    path: Path, vertices: np.ndarray, colours: np.ndarray | None, faces: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY in mm, world frame.

    Args:
        vertices: (N, 3) mm, world frame (stored as float32 x y z).
        colours: (N, 3) uint8 red green blue, or None.
        faces: (F, 3) vertex indices (triangles wound towards the pipe axis), or None.

    The header states the unit and frame: ``comment unit mm`` and ``comment frame ...``.
    """
    n = len(vertices)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment unit mm",
        f"comment frame {FRAME_NOTE}",
        "comment generated by omnipipe",
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
    try:
        with open(path, "wb") as fh:
            fh.write(("\n".join(header) + "\n").encode("ascii"))
            for a, b in _chunks(n):
                rec = np.zeros(b - a, dtype=fields)
                v = vertices[a:b]
                rec["x"], rec["y"], rec["z"] = v[:, 0], v[:, 1], v[:, 2]
                if colours is not None:
                    c = colours[a:b]
                    rec["r"], rec["g"], rec["b"] = c[:, 0], c[:, 1], c[:, 2]
                fh.write(rec.tobytes())
            for a, b in _chunks(0 if faces is None else len(faces)):
                frec = np.zeros(b - a, dtype=[("n", "u1"), ("i", "<i4", (3,))])
                frec["n"] = 3
                frec["i"] = faces[a:b]  # type: ignore[index]
                fh.write(frec.tobytes())
    except OSError as exc:
        raise _fail(path, exc) from None


def write_laz(
    path: Path, points_mm: np.ndarray, colours: np.ndarray, point_frame: np.ndarray | None = None
) -> None:
    """Compressed LAS 1.4 point cloud (point format 7: xyz, RGB), metres, world axes.

    Args:
        points_mm: (N, 3) world frame, mm; stored in metres with a 1e-5 m (0.01 mm)
            scale and an offset at the cloud's minimum rounded down to the centimetre.
        colours: (N, 3) uint8; stored as LAS's 16-bit RGB (x 257).
        point_frame: (N,) keyframe index of each point, stored as ``point_source_id``
            (clipped to 65535), or None.

    The header's system identifier reads "omnipipe world frame, metre"; a WKT VLR holds
    the local coordinate system (:data:`LAS_WKT`).
    """
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.full(3, LAS_SCALE_M)
    # min(x) * c == min(x * c) for c > 0: the offset of the points in metres.
    header.offsets = (
        np.floor(_extent(points_mm)[0] * M_PER_MM * 100) / 100 if len(points_mm) else np.zeros(3)
    )
    header.system_identifier = "omnipipe world frame, metre"
    header.generating_software = "omnipipe"
    header.global_encoding.wkt = True
    header.vlrs.append(WktCoordinateSystemVlr(LAS_WKT))
    try:
        with laspy.open(str(path), mode="w", header=header, laz_backend=laspy.LazBackend.Lazrs) as las:
            for a, b in _chunks(len(points_mm)):
                pts_m = np.asarray(points_mm[a:b], float) * M_PER_MM
                rec = laspy.ScaleAwarePointRecord.zeros(b - a, header=las.header)
                rec.x, rec.y, rec.z = pts_m[:, 0], pts_m[:, 1], pts_m[:, 2]
                rgb = np.asarray(colours[a:b], np.uint16) * 257
                rec.red, rec.green, rec.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
                if point_frame is not None:
                    rec.point_source_id = np.clip(point_frame[a:b], 0, 65535).astype(np.uint16)
                las.write_points(rec)
    except OSError as exc:
        raise _fail(path, exc) from None


def write_e57(path: Path, points_mm: np.ndarray, colours: np.ndarray) -> None:
    """E57 point cloud (one scan, identity pose): metres (E57's unit), world axes.

    Args:
        points_mm: (N >= 1, 3) world frame, mm (stored as single-precision metres, so
            about 0.1 um at a few metres).
        colours: (N, 3) uint8.

    The file's and the scan's GUIDs (pye57 draws them at random) are derived from the
    content, so the same points give the same file, byte for byte. The root holds the
    extension :data:`E57_EXTENSION`'s ``omnipipe:unit`` ("metre") and ``omnipipe:frame``.
    """
    import pye57
    import pye57.e57
    from pye57 import libe57

    path = Path(path)
    digest = hashlib.sha256()
    for a, b in _chunks(len(points_mm)):
        digest.update((np.asarray(points_mm[a:b], float) * M_PER_MM).tobytes())
    for a, b in _chunks(len(points_mm)):
        digest.update(np.asarray(colours[a:b], np.uint8).tobytes())
    guids = (uuid.uuid5(uuid.NAMESPACE_URL, f"omnipipe:e57:{digest.hexdigest()}:{i}") for i in count())
    deterministic = SimpleNamespace(uuid4=lambda: next(guids))
    try:
        # pye57 calls ``uuid.uuid4()`` for each GUID: its own reference to the module is
        # replaced for this write only (no other module's uuid4 changes; a pye57 without
        # that reference writes random GUIDs, as before).
        patch = (
            mock.patch.object(pye57.e57, "uuid", deterministic)
            if hasattr(pye57.e57, "uuid")
            else nullcontext()
        )
        with patch:
            with pye57.E57(str(path), mode="w") as e57:
                e57.image_file.extensionsAdd(*E57_EXTENSION)
                _e57_scan(e57, points_mm, colours, f"omnipipe wall points; {FRAME_NOTE}",
                          str(deterministic.uuid4()))
                prefix = E57_EXTENSION[0]
                e57.root.set(f"{prefix}:unit", libe57.StringNode(e57.image_file, "metre"))
                e57.root.set(f"{prefix}:frame", libe57.StringNode(e57.image_file, FRAME_NOTE))
    except (OSError, RuntimeError) as exc:
        raise OutputError(f"{path}: cannot write E57 ({exc})") from None


def _e57_nodes(e57: Any, parent: Any, kind: str, values: dict[str, float | int]) -> None:
    """Set each of ``values`` on the E57 structure ``parent`` as a FloatNode or IntegerNode."""
    from pye57 import libe57

    node = getattr(libe57, kind)
    for key, value in values.items():
        parent.set(key, node(e57.image_file, value))


def _e57_scan(e57: Any, points_mm: np.ndarray, colours: np.ndarray, name: str, guid: str) -> None:
    """One scan of (N >= 1, 3) ``points_mm`` (stored as single-precision metres) with (N, 3)
    uint8 ``colours``: the nodes, values and order of pye57's ``write_scan_raw``
    (identity pose, no intensity), whose metre and buffer copies held every point; here
    :data:`E57_CHUNK` points at a time (see there), converted :data:`WRITE_CHUNK` at a
    time."""
    import pye57.e57
    from pye57 import libe57

    f, n = e57.image_file, len(points_mm)
    scan = libe57.StructureNode(f)
    scan.set("guid", libe57.StringNode(f, f"{{{guid}}}"))
    scan.set("name", libe57.StringNode(f, name))
    _e57_nodes(e57, scan, "FloatNode", {"temperature": 0, "relativeHumidity": 0, "atmosphericPressure": 0})
    scan.set("description", libe57.StringNode(f, f"pye57 v{pye57.e57.__version__}"))
    box = libe57.StructureNode(f)
    _e57_nodes(e57, box, "IntegerNode", {"rowMinimum": 0, "rowMaximum": n - 1, "columnMinimum": 0,
                                         "columnMaximum": 0, "returnMinimum": 0, "returnMaximum": 0})
    scan.set("indexBounds", box)
    box = libe57.StructureNode(f)
    for c in ("Red", "Green", "Blue"):
        _e57_nodes(e57, box, "IntegerNode", {f"color{c}Minimum": 0, f"color{c}Maximum": 255})
    scan.set("colorLimits", box)
    lo, hi = (v * M_PER_MM for v in _extent(points_mm))  # as the metres' min and max
    rotation, translation = np.array([1, 0, 0, 0]), np.array([0, 0, 0])
    lo_g = e57.to_global(lo.reshape(-1, 3), rotation, translation)[0]
    hi_g = e57.to_global(hi.reshape(-1, 3), rotation, translation)[0]
    box = libe57.StructureNode(f)
    for i, ax in enumerate("xyz"):
        _e57_nodes(e57, box, "FloatNode", {f"{ax}Minimum": lo_g[i], f"{ax}Maximum": hi_g[i]})
    scan.set("cartesianBounds", box)
    pose = libe57.StructureNode(f)
    scan.set("pose", pose)
    for key, axes, values in (("rotation", "wxyz", rotation), ("translation", "xyz", translation)):
        box = libe57.StructureNode(f)
        _e57_nodes(e57, box, "FloatNode", dict(zip(axes, values, strict=True)))
        pose.set(key, box)
    for key in ("acquisitionStart", "acquisitionEnd"):
        box = libe57.StructureNode(f)
        scan.set(key, box)
        box.set("dateTimeValue", libe57.FloatNode(f, 0))
        box.set("isAtomicClockReferenced", libe57.IntegerNode(f, False))
    prototype = libe57.StructureNode(f)
    centre = (hi + lo) / 2
    for i, ax in enumerate("XYZ"):
        prototype.set(f"cartesian{ax}", libe57.FloatNode(f, centre[i], libe57.E57_SINGLE, lo[i], hi[i]))
    names = ["cartesianX", "cartesianY", "cartesianZ", "colorRed", "colorGreen", "colorBlue"]
    for c in names[3:]:
        prototype.set(c, libe57.IntegerNode(f, 0, 0, 255))
    arrays, buffers = e57.make_buffers(names, min(E57_CHUNK, n))
    points = libe57.CompressedVectorNode(f, prototype, libe57.VectorNode(f, True))
    scan.set("points", points)
    e57.data3d.append(scan)
    writer = points.writer(buffers)
    for a, b in _chunks(n, E57_CHUNK):
        for c, d in _chunks(b - a):  # converted a smaller chunk at a time
            pts_m = np.asarray(points_mm[a + c : a + d], float) * M_PER_MM
            cols = np.asarray(colours[a + c : a + d], np.uint8)
            for i, key in enumerate(names):
                arrays[key][c:d] = pts_m[:, i] if i < 3 else cols[:, i - 3]
        writer.write(b - a)
    writer.close()


def write_glb(
    path: Path, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture: np.ndarray | Path
) -> None:
    """Textured binary glTF in metres, y up (opens in Blender, three.js, Windows 3D Viewer).

    Args:
        vertices: (V, 3) world frame, mm; written as ``gltf_from_world_mm(vertices)``.
        faces: (F >= 1, 3) triangles wound towards the pipe axis (vertex normals follow).
        uvs: (V, 2) in [0, 1], v up.
        texture: (H, W, 3) uint8 atlas, or the path of its PNG as :func:`texture_png`
            wrote it (embedded as read, a chunk at a time: the same file).

    The material is double-sided, fully rough and not metallic; ``asset.extras`` records
    the unit, the source frame and :data:`GLTF_FROM_WORLD`. The file is trimesh's
    ``export_glb`` of the mesh (with vertex normals), byte for byte, written as a stream:
    a first pass over the arrays (a chunk at a time) gives the JSON header its counts,
    extents and buffer lengths, a second writes the binary chunk; what is held is the
    (V, 3) vertex normals (and, given the atlas, its PNG).
    """
    import io

    if isinstance(texture, Path):
        png_parts = functools.partial(_file_parts, texture)
    else:
        png = io.BytesIO()
        texture_png(png, texture)
        png_parts = lambda: iter([png.getbuffer()])  # noqa: E731 - the PNG's bytes in place
    normals = _vertex_normals(vertices, np.asarray(faces), gltf_from_world_mm)
    # trimesh's buffers in its order: indices, positions, the texture, UVs, normals.
    streams: list[Callable[[], Iterator[np.ndarray | memoryview]]] = [
        lambda: (np.asarray(faces[a:b]).astype(np.uint32).ravel() for a, b in _chunks(len(faces))),
        lambda: (gltf_from_world_mm(vertices[a:b]).astype(np.float32) for a, b in _chunks(len(vertices))),
        png_parts,
        lambda: (_gltf_uv(uvs[a:b]) for a, b in _chunks(len(uvs))),
        lambda: (_unitized(normals[a:b]).astype(np.float32) for a, b in _chunks(len(normals))),
    ]
    stats = [_GlbStats.of(stream()) for stream in streams]
    views, view_of = _glb_views(stats)
    tree = _glb_tree(stats, view_of, len(vertices), views)
    content = json.dumps(tree, separators=(",", ":"))
    content += (4 - ((len(content) + 20) % 4)) * " "  # the binary chunk 4-byte aligned
    text = content.encode("utf-8")
    body = sum(v["byteLength"] for v in views)
    try:
        with open(path, "wb") as fh:
            fh.write(struct.pack("<4sII", b"glTF", 2, len(text) + body + 28))
            fh.write(struct.pack("<I4s", len(text), b"JSON") + text)
            fh.write(struct.pack("<I4s", body, b"BIN\0"))
            for k, stream in enumerate(streams):
                if view_of[k] in view_of[:k]:
                    continue  # the same bytes as an earlier buffer: its view is shared
                for part in stream():
                    fh.write(part if isinstance(part, memoryview) else part.tobytes())
                fh.write(bytes(-stats[k].length % 4))
    except OSError as exc:
        raise _fail(path, exc) from None


def texture_png(dst: Path | BinaryIO, texture: np.ndarray) -> None:
    """The (H, W, 3) uint8 ``texture`` as PNG into ``dst`` (a path or a binary file):
    the bytes model.glb embeds and model_texture.png holds. Encoded a band of rows at a
    time (:func:`omnipipe.model.png.write_png`): no copy of the atlas is held."""
    from omnipipe.model.png import write_png

    write_png(dst, texture)


def _file_parts(path: Path, size: int = 1 << 20) -> Iterator[memoryview]:
    """The bytes of the file ``path``, ``size`` at a time."""
    with open(path, "rb") as fh:
        while chunk := fh.read(size):
            yield memoryview(chunk)


@dataclass
class _GlbStats:
    """One GLB buffer's byte length, content digest and (arrays) value count and
    per-column extremes, gathered a chunk at a time."""

    length: int = 0
    digest: str = ""
    count: int = 0
    low: np.ndarray | None = None
    high: np.ndarray | None = None

    @staticmethod
    def of(parts: Iterator[np.ndarray | memoryview]) -> _GlbStats:
        st, h = _GlbStats(), hashlib.sha256()
        for part in parts:
            raw = part if isinstance(part, memoryview) else part.tobytes()
            st.length += len(raw)
            h.update(raw)
            if isinstance(part, np.ndarray) and len(part):
                flat = part.reshape(len(part), -1)
                st.count += len(part)
                lo, hi = flat.min(axis=0), flat.max(axis=0)
                st.low = lo if st.low is None else np.minimum(st.low, lo)
                st.high = hi if st.high is None else np.maximum(st.high, hi)
        st.digest = h.hexdigest()
        return st


def _gltf_uv(uv: np.ndarray) -> np.ndarray:
    """(n, 2) UVs, v up -> glTF's (v down), float32 (trimesh's conversion)."""
    out = np.array(uv, float)[:, :2]
    out[:, 1] = 1.0 - out[:, 1]
    return out.astype(np.float32)


def _unitized(v: np.ndarray) -> np.ndarray:
    from trimesh import util

    return util.unitize(v)


def _glb_views(stats: list[_GlbStats]) -> tuple[list[dict[str, int]], list[int]]:
    """The buffer views (each buffer padded to 4 bytes, laid end to end) and each
    buffer's view: a buffer whose bytes an earlier one holds shares its view (trimesh
    stores equal bytes once)."""
    views: list[dict[str, int]] = []
    view_of: list[int] = []
    seen: dict[tuple[int, str], int] = {}
    pos = 0
    for st in stats:
        key = (st.length, st.digest)
        if key not in seen:
            seen[key] = len(views)
            size = st.length + (-st.length % 4)
            views.append({"buffer": 0, "byteOffset": pos, "byteLength": size})
            pos += size
        view_of.append(seen[key])
    return views, view_of


def _extremes(st: _GlbStats) -> dict[str, list[float] | list[int]]:
    if st.low is None or st.high is None:  # an empty array (write_glb is given faces)
        return {}
    return {"max": st.high.tolist(), "min": st.low.tolist()}


def _glb_tree(
    stats: list[_GlbStats], view_of: list[int], n_vertices: int, views: list[dict[str, int]]
) -> dict[str, Any]:
    """The GLB's JSON: trimesh's tree of one textured mesh with normals (keys in its
    order) and this module's ``asset.extras``."""
    faces, positions, _image, uv, normals = stats
    accessors = [
        {"componentType": 5125, "type": "SCALAR", "bufferView": view_of[0], "count": faces.count,
         **_extremes(faces)},
        {"componentType": 5126, "type": "VEC3", "byteOffset": 0, "bufferView": view_of[1],
         "count": positions.count, **_extremes(positions)},
        {"componentType": 5126, "type": "VEC2", "byteOffset": 0, "bufferView": view_of[3],
         "count": uv.count, **_extremes(uv)},
        {"componentType": 5126, "count": n_vertices, "type": "VEC3", "byteOffset": 0,
         "bufferView": view_of[4], **_extremes(normals)},
    ]
    return {
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "asset": {
            "version": "2.0",
            "generator": "https://github.com/mikedh/trimesh",
            "extras": {
                "unit": "metre",
                "source_frame": FRAME_NOTE + ", mm",
                "gltf_from_world": GLTF_FROM_WORLD.tolist(),
                "gltf_from_world_note": "x = world z (along the pipe), y = -world y, z = world x",
            },
        },
        "accessors": accessors,
        "meshes": [{"name": "geometry_0", "extras": {}, "primitives": [{
            "attributes": {"POSITION": 1, "TEXCOORD_0": 2, "NORMAL": 3},
            "indices": 0, "mode": 4, "material": 0}]}],
        "images": [{"bufferView": view_of[2], "mimeType": "image/png"}],
        "textures": [{"source": 0}],
        "materials": [{
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "roughnessFactor": 1.0,
                                     "metallicFactor": 0.0},
            "name": "pipe_wall", "doubleSided": True}],
        "nodes": [{"name": "geometry_0", "mesh": 0}],
        "buffers": [{"byteLength": sum(v["byteLength"] for v in views)}],
        "bufferViews": views,
    }


def _vertex_normals(
    vertices: np.ndarray,
    faces: np.ndarray,
    convert: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """(V, 3) unit vertex normals of the mesh (``vertices`` (V, 3), ``faces`` (F, 3);
    ``convert``: applied to the vertices' rows first, e.g. :func:`gltf_from_world_mm`):
    trimesh's ``Trimesh.vertex_normals`` bit for bit (each face's unit normal weighted by
    its corner angle, summed face by face in face order, then unitized), computed
    :data:`WRITE_CHUNK` faces at a time: trimesh's own sparse matrix of every corner and
    its per-face arrays were the GLB's largest cost (70 MB for 280,000 faces); a chunk
    of :data:`NORMALS_CHUNK` faces costs about 6 MB. The normals are made in the run's
    scratch (:mod:`omnipipe.spill`)."""
    from trimesh import triangles, util

    from omnipipe.spill import zeros_on_disk

    # (V, 3) float64, held through the GLB's writing: in the run's scratch (omnipipe.spill).
    summed = zeros_on_disk((len(vertices), 3), np.float64)
    for a, b in _chunks(len(faces), min(WRITE_CHUNK, NORMALS_CHUNK)):
        idx = np.asarray(faces[a:b])
        tri = vertices[idx.ravel()]
        tri = (tri if convert is None else convert(tri)).reshape(-1, 3, 3)
        unit, valid = triangles.normals(triangles=tri, crosses=triangles.cross(tri))
        normals = np.zeros((b - a, 3))
        normals[valid] = unit
        ok = (normals**2).sum(axis=1) > 0.5  # trimesh's test of a face's normal
        corners = triangles.angles(tri)[ok][:, :, None] * normals[ok][:, None, :]
        np.add.at(summed, idx[ok].ravel(), corners.reshape(-1, 3))
    for a, b in _chunks(len(summed)):  # row by row: in place, not a second (V, 3) array
        summed[a:b] = util.unitize(summed[a:b])
    return summed


def _rows(fmt: str, values: np.ndarray) -> str:
    """The (N, K) ``values`` as N lines of ``fmt`` (K %-fields), joined by newlines: one
    %-format of the whole table (3x faster than a formatted string per row)."""
    if len(values) == 0:
        return ""
    return ((fmt + "\n") * len(values) % tuple(values.ravel().tolist()))[:-1]


_ROWS_CHUNK = 1 << 15
"""Rows formatted at once by :func:`_write_rows` (their Python numbers, about 40 bytes
a value, are a chunk's, not the model's)."""


def _write_rows(
    fh: TextIO, fmt: str, values: np.ndarray, convert: Callable[[np.ndarray], np.ndarray] = np.asarray
) -> None:
    """Write :func:`_rows` of ``convert(chunk)`` for each chunk of rows of ``values`` to
    ``fh`` (a converted copy of a chunk only, never of all rows)."""
    for a, b in _chunks(len(values), _ROWS_CHUNK):
        if a:
            fh.write("\n")
        fh.write(_rows(fmt, np.asarray(convert(values[a:b]), float)))


def _obj_face_rows(faces: np.ndarray) -> np.ndarray:
    """(F, 3) 0-based faces -> (F, 6) OBJ ``v/vt`` index pairs (1-based)."""
    return np.repeat(np.asarray(faces, np.int64) + 1, 2, axis=1)


def write_obj(
    path: Path, vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture: np.ndarray | Path
) -> None:
    """Wavefront OBJ + MTL + PNG texture, in metres with the GLB's axes.

    Args:
        vertices: (V, 3) world frame, mm; written as ``gltf_from_world_mm(vertices)``.
        faces: (F, 3) triangles wound towards the pipe axis.
        uvs: (V, 2) in [0, 1], v up (OBJ's own convention).
        texture: (H, W, 3) uint8, written as :data:`OBJ_TEXTURE` beside ``path``, or
            the path of that file already written by :func:`texture_png` (kept as it is).

    OBJ has no unit field: comment lines at the top state unit and axes. ``path.stem +
    ".mtl"`` holds one material whose ``map_Kd`` is the texture.
    """
    path = Path(path)
    mtl = path.with_suffix(".mtl")
    lines = [
        "# omnipipe pipe wall model",
        "# unit: metre",
        f"# axes: x = world z (along the pipe), y (up) = -world y, z = world x; {FRAME_NOTE}",
        "# faces are wound so their normals point towards the pipe axis",
        f"mtllib {mtl.name}",
        "o pipe_wall",
    ]
    body = [
        lambda fh: fh.write("\n".join(lines)),
        lambda fh: _write_rows(fh, "v %.7f %.7f %.7f", vertices, gltf_from_world_mm),
        lambda fh: _write_rows(fh, "vt %.6f %.6f", uvs),
        lambda fh: fh.write("usemtl pipe_wall\ns off"),
        lambda fh: _write_rows(fh, "f %d/%d %d/%d %d/%d", faces, _obj_face_rows),
    ]
    material = "\n".join(
        [
            "# omnipipe pipe wall material",
            "newmtl pipe_wall",
            "Ka 1.000 1.000 1.000",
            "Kd 1.000 1.000 1.000",
            "Ks 0.000 0.000 0.000",
            "d 1.0",
            "illum 1",
            f"map_Kd {OBJ_TEXTURE}",
        ]
    )
    try:
        # The parts joined by newlines, written a chunk of rows at a time.
        with open(path, "w", encoding="ascii") as fh:
            for i, part in enumerate(body):
                if i:
                    fh.write("\n")
                part(fh)
            fh.write("\n")
        mtl.write_text(material + "\n", encoding="ascii")
        if not isinstance(texture, Path):
            texture_png(path.parent / OBJ_TEXTURE, texture)
        elif texture.resolve() != (path.parent / OBJ_TEXTURE).resolve():
            shutil.copyfile(texture, path.parent / OBJ_TEXTURE)
    except OSError as exc:
        raise _fail(path, exc) from None


def _write_rgba_png(path: Path, image: np.ndarray, alpha: np.ndarray) -> None:
    """The (H, W, 3) uint8 ``image`` with the (H, W) bool ``alpha`` as 255 / 0 (the
    (H, W, 4) ``np.dstack`` of the two) as a PNG at ``path``, made and encoded a band of
    :data:`_RGBA_ROWS` rows at a time (:class:`omnipipe.model.png.PngWriter`): neither
    the image nor its RGBA copy is held whole; an image in the run's scratch
    (:mod:`omnipipe.spill`) has its pages dropped after each band."""
    from omnipipe.model.png import PngWriter
    from omnipipe.spill import drop_pages, is_on_disk

    h, w = alpha.shape
    spilled = is_on_disk(image) or is_on_disk(alpha)
    band = np.empty((_RGBA_ROWS, w, 4), np.uint8)
    with open(path, "wb") as fh:
        writer = PngWriter(fh, w, h, 4)
        for top in range(0, h, _RGBA_ROWS):
            rows = band[: min(_RGBA_ROWS, h - top)]
            rows[..., :3] = image[top : top + len(rows)]
            rows[..., 3] = np.where(alpha[top : top + len(rows)], 255, 0)
            writer.write_rows(rows)
            if spilled:
                drop_pages()
        writer.close()


_RGBA_ROWS = 256
"""Rows of the unrolled image :func:`_write_rgba_png` makes and encodes at a time."""


def write_outputs(result: ModelResult, out_dir: Path) -> None:
    """All model files into ``out_dir`` (see the module docstring for units and axes).

    Always: points.ply, mesh.ply, points.laz. With points: points.e57. With a texture:
    unrolled.png, model.glb, model.obj, model.mtl, model_texture.png.
    """
    from omnipipe.memory import release_freed_memory

    out_dir = Path(out_dir)
    write_ply(out_dir / "points.ply", result.points_in_world, result.colours)
    write_ply(out_dir / "mesh.ply", result.mesh_vertices, result.colours, result.mesh_faces)
    write_laz(out_dir / "points.laz", result.points_in_world, result.colours, result.point_frame)
    if len(result.points_in_world):
        write_e57(out_dir / "points.e57", result.points_in_world, result.colours)
    release_freed_memory()  # each writer's chunks: not under the next one's
    if result.unrolled is not None:
        try:
            _write_rgba_png(out_dir / "unrolled.png", result.unrolled.image, result.unrolled.alpha)
        except OSError as exc:
            raise _fail(out_dir / "unrolled.png", exc) from None
    if (
        result.texture is not None
        and result.textured_faces is not None
        and len(result.textured_faces)
    ):
        args = (result.textured_vertices, result.textured_faces, result.textured_uvs)
        # The atlas's PNG encoded once (PIL copies the image whole to encode it): the
        # OBJ's texture file, which the GLB embeds as read.
        png = out_dir / OBJ_TEXTURE
        try:
            texture_png(png, result.texture)
        except OSError as exc:
            raise _fail(png, exc) from None
        release_freed_memory()
        write_glb(out_dir / "model.glb", *args, png)
        release_freed_memory()
        write_obj(out_dir / "model.obj", *args, png)
        release_freed_memory()

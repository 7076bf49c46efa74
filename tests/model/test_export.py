"""Model files read back with maintained readers: units, bounds, axes and normals.

A synthetic 200 mm pipe (radius 100 mm, 300 mm long) is meshed by the model stage's
own mesher and orientation and written with :func:`omnipipe.model.write_outputs`;
trimesh (GLB, OBJ, PLY), laspy (LAZ) and pye57 (E57) read the files back.
"""

from __future__ import annotations

import functools
import json
import math
import struct
from pathlib import Path

import laspy
import numpy as np
import pye57
import pytest
import trimesh
from PIL import Image

from omnipipe.model import (
    ModelResult,
    mesh_unrolled,
    orient_towards_axis,
    textured_mesh,
    write_outputs,
)
from omnipipe.model.export import write_e57
from omnipipe.model.texture_grid import UnrolledImage

RADIUS_MM = 100.0
LENGTH_MM = 300.0


def synthetic_pipe(direction: float, seed: int = 0) -> ModelResult:
    """Rings of a straight pipe along world z (direction +1 or -1 = direction of travel).

    The arc is measured from world x towards y and the axial position grows along the
    travel, as in the analysis stage; with direction -1 the unrolled winding is mirrored
    against 3-D, which :func:`orient_towards_axis` must notice.
    """
    rng = np.random.default_rng(seed)
    rings, per_ring = 61, 120
    axial = np.repeat(np.linspace(0.0, LENGTH_MM, rings), per_ring)
    theta = np.tile(np.linspace(0.0, 2 * math.pi, per_ring, endpoint=False), rings)
    theta = (theta + rng.uniform(-0.01, 0.01, theta.size)) % (2 * math.pi)
    r = RADIUS_MM + rng.normal(0.0, 0.05, theta.size)
    pts = np.column_stack([r * np.cos(theta), r * np.sin(theta), direction * axial])
    frame = np.repeat(np.arange(rings), per_ring)
    colours = rng.integers(0, 256, (len(pts), 3), dtype=np.uint8)
    circ = 2 * math.pi * RADIUS_MM
    arc = theta * RADIUS_MM
    faces = mesh_unrolled(arc, axial, pts, circ, 2.0)
    faces = orient_towards_axis(faces, arc, axial, circ, pts, frame)
    mm_per_px = 2.0
    h, w = int(LENGTH_MM / mm_per_px) + 1, int(round(circ / mm_per_px))
    image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    unrolled = UnrolledImage(image, np.ones((h, w), bool), mm_per_px, 0.0, circ)
    verts, tfaces, uvs, atlas = textured_mesh(faces, pts, arc, axial, unrolled)
    return ModelResult(
        pts, colours, frame, pts, faces, verts, tfaces, uvs, atlas, unrolled=unrolled
    )


def inward_fraction(vertices: np.ndarray, faces: np.ndarray, axis: int) -> float:
    """Fraction of faces whose winding normal points towards the line along ``axis``."""
    p = vertices[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = -p.mean(axis=1)
    inward[:, axis] = 0.0
    return float(np.mean(np.sum(n * inward, axis=1) > 0))


def glb_json(path: Path) -> dict:
    """The JSON chunk of a binary glTF file."""
    data = path.read_bytes()
    magic, _, _ = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF"
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    return json.loads(data[20 : 20 + length])


@pytest.fixture(scope="module", params=[1.0, -1.0], ids=["forward", "backward"])
def written(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    res = synthetic_pipe(request.param)
    out = tmp_path_factory.mktemp("export")
    write_outputs(res, out)
    return res, out, request.param


def expected_gltf_m(world_mm: np.ndarray) -> np.ndarray:
    """Documented mapping: glTF x = world z, y = -world y, z = world x; metres."""
    return np.column_stack([world_mm[:, 2], -world_mm[:, 1], world_mm[:, 0]]) / 1000.0


def test_faces_point_towards_the_axis_in_the_world(written) -> None:
    res, _, _ = written
    assert inward_fraction(res.mesh_vertices, res.mesh_faces, axis=2) > 0.95
    assert inward_fraction(res.textured_vertices, res.textured_faces, axis=2) > 0.95


def test_glb_is_in_metres_y_up_double_sided_with_inward_normals(written) -> None:
    res, out, direction = written
    mesh = trimesh.load(out / "model.glb", force="mesh", process=False)
    v = np.asarray(mesh.vertices)
    # Units: a 200 mm pipe has a radius of 0.1 (glTF metres) around the glTF x axis.
    radial = np.hypot(v[:, 1], v[:, 2])
    assert np.all(np.abs(radial - RADIUS_MM / 1000) < 0.5e-3)  # 0.5 mm: noise is 0.05 mm
    lo, hi = sorted([0.0, direction * LENGTH_MM / 1000])
    assert np.allclose(mesh.bounds[:, 0], [lo, hi], atol=1e-6)
    assert np.allclose(v, expected_gltf_m(res.textured_vertices), atol=1e-6)
    # Normals: the faces' winding and the stored vertex normals face the pipe axis (glTF x).
    assert inward_fraction(v, np.asarray(mesh.faces), axis=0) > 0.95
    vn = np.asarray(mesh.vertex_normals)
    towards = -v.copy()
    towards[:, 0] = 0.0
    assert np.mean(np.sum(vn * towards, axis=1) > 0) > 0.95
    tree = glb_json(out / "model.glb")
    assert [m["doubleSided"] for m in tree["materials"]] == [True]
    assert tree["asset"]["extras"]["unit"] == "metre"
    assert "NORMAL" in tree["meshes"][0]["primitives"][0]["attributes"]
    assert mesh.visual.material.baseColorTexture.size == res.texture.shape[1::-1]


def test_ply_states_unit_and_frame_and_keeps_mm(written) -> None:
    res, out, _ = written
    for name in ("points.ply", "mesh.ply"):
        head = (out / name).read_bytes().split(b"end_header")[0].decode("ascii")
        assert "comment unit mm" in head.splitlines()
        assert "comment frame world = first registered rig frame" in head
    cloud = trimesh.load(out / "points.ply", process=False)
    assert np.allclose(cloud.vertices, res.points_in_world, atol=1e-3)
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert np.array_equal(mesh.faces, res.mesh_faces)
    assert inward_fraction(np.asarray(mesh.vertices), np.asarray(mesh.faces), axis=2) > 0.95


def test_laz_holds_every_point_in_metres_to_a_hundredth_of_a_mm(written) -> None:
    res, out, _ = written
    las = laspy.read(out / "points.laz")
    assert las.header.point_count == len(res.points_in_world)
    assert np.allclose(las.header.scales, 1e-5)
    xyz_mm = np.column_stack([las.x, las.y, las.z]) * 1000.0
    assert np.max(np.abs(xyz_mm - res.points_in_world)) <= 0.01
    rgb = np.column_stack([las.red, las.green, las.blue])
    assert np.array_equal(rgb // 257, res.colours) and np.all(rgb % 257 == 0)
    assert np.array_equal(las.point_source_id, res.point_frame)
    assert "metre" in las.header.system_identifier
    assert any("metre" in str(getattr(v, "string", "")) for v in las.header.vlrs)


def test_e57_holds_every_point_in_metres(written) -> None:
    res, out, _ = written
    with pye57.E57(str(out / "points.e57")) as e57:
        assert e57.scan_count == 1
        data = e57.read_scan_raw(0)
    xyz_mm = np.column_stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]]) * 1e3
    assert len(xyz_mm) == len(res.points_in_world)
    assert np.max(np.abs(xyz_mm - res.points_in_world)) < 1e-3  # single precision metres
    rgb = np.column_stack([data["colorRed"], data["colorGreen"], data["colorBlue"]])
    assert np.array_equal(rgb, res.colours)


def test_obj_resolves_its_texture_and_matches_the_glb(written) -> None:
    res, out, _ = written
    text = (out / "model.obj").read_text(encoding="ascii")
    assert "# unit: metre" in text.splitlines()
    mesh = trimesh.load(out / "model.obj", process=False, maintain_order=True)
    assert np.allclose(mesh.vertices, expected_gltf_m(res.textured_vertices), atol=1e-6)
    assert np.array_equal(mesh.faces, res.textured_faces)
    assert inward_fraction(np.asarray(mesh.vertices), np.asarray(mesh.faces), axis=0) > 0.95
    image = mesh.visual.material.image
    assert image is not None and image.size == res.texture.shape[1::-1]
    assert np.array_equal(np.asarray(image.convert("RGB")), res.texture)
    assert np.allclose(mesh.visual.uv, res.textured_uvs, atol=1e-6)


def test_the_same_points_give_the_same_e57_file_byte_for_byte(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    pts = rng.normal(0.0, 100.0, (500, 3))
    cols = rng.integers(0, 256, (500, 3), dtype=np.uint8)
    write_e57(tmp_path / "a.e57", pts, cols)
    write_e57(tmp_path / "b.e57", pts, cols)
    assert (tmp_path / "a.e57").read_bytes() == (tmp_path / "b.e57").read_bytes()
    with pye57.E57(str(tmp_path / "a.e57")) as e57:  # still a readable scan of the points
        assert np.allclose(e57.read_scan_raw(0)["cartesianX"], pts[:, 0] / 1000.0, atol=1e-7)
    moved = pts.copy()
    moved[0, 0] += 1.0  # other points, other GUIDs
    write_e57(tmp_path / "c.e57", moved, cols)
    assert (tmp_path / "a.e57").read_bytes() != (tmp_path / "c.e57").read_bytes()


def test_every_3d_file_states_its_unit_and_holds_the_same_point_at_its_scale(written) -> None:
    """Each file's own unit statement (PLY comment, LAS WKT, E57 root field, glTF
    asset.extras, OBJ comment) and the same wall point read back in it: mm where it says
    mm, metres (x 1e-3) where it says metres; model_files lists every file with its unit."""
    from omnipipe.model.export import model_files

    res, out, _ = written
    listed = model_files(res)
    assert set(listed) == {"points.ply", "mesh.ply", "points.laz", "points.e57", "model.glb", "model.obj"}
    p_mm = res.points_in_world[7]
    found: dict[str, tuple[str, np.ndarray]] = {}
    for name in ("points.ply", "mesh.ply"):
        header = (out / name).read_bytes().split(b"end_header")[0].decode("ascii")
        unit = "mm" if "comment unit mm" in header.splitlines() else "?"
        found[name] = unit, np.asarray(trimesh.load(out / name, process=False).vertices)[7]
    las = laspy.read(out / "points.laz")
    wkt = "".join(str(getattr(v, "string", "")) for v in las.header.vlrs)
    found["points.laz"] = ("m" if 'UNIT["metre",1]' in wkt else "?"), np.array([las.x[7], las.y[7], las.z[7]])
    with pye57.E57(str(out / "points.e57")) as e57:
        unit = e57.root["omnipipe:unit"].value()
        d = e57.read_scan_raw(0)
    found["points.e57"] = ("m" if unit == "metre" else "?"), np.array(
        [d["cartesianX"][7], d["cartesianY"][7], d["cartesianZ"][7]])
    gltf_unit = glb_json(out / "model.glb")["asset"]["extras"]["unit"]
    glb = trimesh.load(out / "model.glb", process=False, force="mesh")
    obj_text = (out / "model.obj").read_text(encoding="ascii").splitlines()
    v_obj = np.array([float(x) for x in next(ln for ln in obj_text if ln.startswith("v ")).split()[1:]])
    # The viewer models' vertex 0 is the textured mesh's vertex 0 (turned to glTF axes).
    found["model.glb"] = ("m" if gltf_unit == "metre" else "?"), np.asarray(glb.vertices)[0]
    found["model.obj"] = ("m" if "# unit: metre" in obj_text else "?"), v_obj
    for name, (unit, value) in found.items():
        assert unit == listed[name]["unit"], name
        ref = p_mm
        if name.startswith("model."):
            ref = expected_gltf_m(res.textured_vertices[:1])[0] * 1e3  # the glTF axes, mm
        scale = 1.0 if unit == "mm" else 1e-3
        assert np.allclose(value, ref * scale, atol=0.01 * scale), name  # LAS: 0.01 mm steps


def test_files_written_a_chunk_at_a_time_equal_those_written_whole(
    written, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each writer converts and writes WRITE_CHUNK points (faces) at a time: with chunks of
    a few hundred (7,320 points, 14,400 faces) every file is the one-chunk file, byte for
    byte (E57 handed to libE57 in chunks too: the same points, colours and header); the
    GLB's vertex normals are trimesh's own (the file trimesh writes alone)."""
    from omnipipe.model import export

    res, whole, _ = written
    monkeypatch.setattr(export, "WRITE_CHUNK", 999)
    monkeypatch.setattr(export, "_ROWS_CHUNK", 333)
    write_outputs(res, tmp_path)
    names = sorted(p.name for p in whole.iterdir())
    assert names == sorted(p.name for p in tmp_path.iterdir())
    assert {"points.laz", "points.e57", "model.glb", "model.obj", "mesh.ply"} <= set(names)
    for name in names:
        assert (tmp_path / name).read_bytes() == (whole / name).read_bytes(), name
    monkeypatch.setattr(export, "E57_CHUNK", 1001)
    write_e57(tmp_path / "chunked.e57", res.points_in_world, res.colours)
    scans = [pye57.E57(str(p)).read_scan_raw(0) for p in (whole / "points.e57", tmp_path / "chunked.e57")]
    assert scans[0].keys() == scans[1].keys()
    assert all(np.array_equal(scans[0][k], scans[1][k]) for k in scans[0])
    mesh = trimesh.Trimesh(
        export.gltf_from_world_mm(res.textured_vertices), res.textured_faces, process=False
    )
    ours = export._vertex_normals(mesh.vertices, np.asarray(res.textured_faces))
    assert np.array_equal(ours, mesh.vertex_normals)


def test_writers_of_a_model_in_the_scratch_drop_its_pages_after_each_chunk(
    written, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The model's arrays in the run's scratch (as the pipeline hands them to the
    writers): each writer drops the scratch's pages after each chunk it used (not only
    when the run's dropping thread next wakes), and every file is the one written from
    the arrays in memory, byte for byte."""
    from omnipipe import spill
    from omnipipe.model import export
    from omnipipe.pipeline.stage_calls import model_on_disk

    res, whole, _ = written
    monkeypatch.setattr(export, "WRITE_CHUNK", 999)
    monkeypatch.setattr(export, "_ROWS_CHUNK", 333)
    drops = []
    real = spill.drop_pages
    monkeypatch.setattr(spill, "drop_pages", lambda: (drops.append(1), real())[1])
    on_disk = model_on_disk(res)
    assert spill.is_on_disk(on_disk.textured_faces) and spill.is_on_disk(on_disk.points_in_world)
    write_outputs(on_disk, tmp_path)
    for name in sorted(p.name for p in whole.iterdir()):
        assert (tmp_path / name).read_bytes() == (whole / name).read_bytes(), name
    n_v, n_f = len(res.textured_vertices), len(res.textured_faces)
    glb = 2 * (-(-n_f // 999) + 3 * -(-n_v // 999))  # two passes over faces, positions, UVs, normals
    obj = -(-n_v // 333) * 2 + -(-n_f // 333)
    assert len(drops) >= glb + obj


def trimesh_glb(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture: np.ndarray) -> bytes:
    """The GLB trimesh's own ``export_glb`` writes of the same textured mesh (vertex
    normals, material and ``asset.extras`` as :func:`write_glb` documents them)."""
    from PIL import Image

    from omnipipe.image import PNG_COMPRESS_LEVEL
    from omnipipe.model import export

    image = Image.fromarray(np.ascontiguousarray(texture))
    image.encoderinfo = {"compress_level": PNG_COMPRESS_LEVEL}
    material = trimesh.visual.material.PBRMaterial(
        name="pipe_wall", baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0,
        doubleSided=True,
    )
    viewer = export.gltf_from_world_mm(vertices)
    mesh = trimesh.Trimesh(
        vertices=viewer, faces=faces, process=False,
        visual=trimesh.visual.TextureVisuals(uv=uvs, material=material),
        vertex_normals=export._vertex_normals(viewer, np.asarray(faces)),
    )

    def annotate(tree: dict) -> None:
        tree["asset"]["extras"] = {
            "unit": "metre",
            "source_frame": export.FRAME_NOTE + ", mm",
            "gltf_from_world": export.GLTF_FROM_WORLD.tolist(),
            "gltf_from_world_note": "x = world z (along the pipe), y = -world y, z = world x",
        }

    return trimesh.exchange.gltf.export_glb(
        trimesh.Scene(mesh), include_normals=True, tree_postprocessor=annotate
    )


@pytest.mark.parametrize("chunk", [100_000, 997])
def test_glb_streamed_is_trimeshs_file_byte_for_byte(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, chunk: int
) -> None:
    """write_glb streams the binary chunk after a JSON header built from counts and
    extents: the file is trimesh's export_glb of the same mesh, byte for byte, whether
    its arrays go in one chunk or in chunks of 997 rows (a pipe mesh with degenerate
    faces and unused vertices; a texture whose PNG is not a multiple of 4 bytes). The
    texture's PNG is PIL's here (trimesh encodes it so); omnipipe's own streamed PNG,
    which decodes to the same pixels, is embedded as it is."""
    from omnipipe.model import export

    monkeypatch.setattr(export, "WRITE_CHUNK", chunk)
    monkeypatch.setattr(export, "texture_png", pil_texture_png)
    rng = np.random.default_rng(3)
    cols, rows = 90, 40
    theta, z = np.meshgrid(np.linspace(0, 2 * np.pi, cols, endpoint=False), np.arange(rows) * 2.0)
    v = np.column_stack([150 * np.cos(theta.ravel()), 150 * np.sin(theta.ravel()), z.ravel()])
    v += rng.normal(0, 0.3, v.shape)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    f = f[rng.permutation(len(f))].astype(np.int32)
    f[:5, 1] = f[:5, 0]  # degenerate faces
    f = f[f.max(axis=1) < len(v) - 7]  # the last vertices unused
    uv = rng.random((len(v), 2))
    tex = rng.integers(0, 256, (31, 43, 3), dtype=np.uint8)
    export.write_glb(tmp_path / "m.glb", v, f, uv, tex)
    assert (tmp_path / "m.glb").read_bytes() == trimesh_glb(v, f, uv, tex)
    # Given the texture's PNG file (as write_outputs does: encoded once for GLB and OBJ),
    # read a few bytes at a time: the same file.
    monkeypatch.setattr(export, "_file_parts", functools.partial(export._file_parts, size=1000))
    export.texture_png(tmp_path / "t.png", tex)
    export.write_glb(tmp_path / "p.glb", v, f, uv, tmp_path / "t.png")
    assert (tmp_path / "p.glb").read_bytes() == trimesh_glb(v, f, uv, tex)
    (tmp_path / "a").mkdir()
    export.write_obj(tmp_path / "a" / "m.obj", v, f, uv, tex)
    export.write_obj(tmp_path / "m.obj", v, f, uv, tmp_path / "t.png")
    for name in ("m.obj", "m.mtl", export.OBJ_TEXTURE):
        assert (tmp_path / name).read_bytes() == (tmp_path / "a" / name).read_bytes(), name
    monkeypatch.undo()
    export.write_glb(tmp_path / "s.glb", v, f, uv, tex)  # the streamed PNG inside
    export.texture_png(tmp_path / "s.png", tex)
    (tree, views), (pil_tree, pil_views) = _glb_parts(tmp_path / "s.glb"), _glb_parts(tmp_path / "m.glb")
    image_view = tree["images"][0]["bufferView"]
    png_bytes = (tmp_path / "s.png").read_bytes()  # in its view, padded to 4 bytes
    assert views[image_view] == png_bytes + bytes(len(views[image_view]) - len(png_bytes))
    assert len(views[image_view]) - len(png_bytes) < 4
    assert [b for k, b in enumerate(views) if k != image_view] == [
        b for k, b in enumerate(pil_views) if k != image_view
    ]
    for t in (tree, pil_tree):
        for view in t["bufferViews"]:
            view.pop("byteOffset", None), view.pop("byteLength")
        t["buffers"][0].pop("byteLength")
    assert tree == pil_tree
    with Image.open(tmp_path / "s.png") as im:
        assert np.array_equal(np.asarray(im), tex)


def _glb_parts(path: Path) -> tuple[dict, list[bytes]]:
    """A GLB file's JSON tree and each of its buffer views' bytes."""
    data = path.read_bytes()
    (n,) = struct.unpack("<I", data[12:16])
    tree = json.loads(data[20 : 20 + n])
    binary = data[20 + n + 8 :]
    return tree, [binary[v.get("byteOffset", 0) : v.get("byteOffset", 0) + v["byteLength"]] for v in tree["bufferViews"]]


def pil_texture_png(dst, texture: np.ndarray) -> None:
    """PIL's PNG of ``texture`` (the bytes trimesh embeds)."""
    from omnipipe.image import PNG_COMPRESS_LEVEL

    Image.fromarray(np.ascontiguousarray(texture)).save(dst, format="png", compress_level=PNG_COMPRESS_LEVEL)


def test_unrolled_png_from_the_scratch_decodes_to_the_stacked_image(monkeypatch, tmp_path: Path) -> None:
    """unrolled.png is made and encoded a band of rows at a time from an image and a
    mask in the run's scratch: it decodes to the pixels of ``np.dstack`` of the two."""
    from PIL import Image

    import omnipipe.model.export as export
    from omnipipe.spill import on_disk

    monkeypatch.setattr(export, "_RGBA_ROWS", 7)  # many bands, a ragged last one
    rng = np.random.default_rng(14)
    image = rng.integers(0, 256, (45, 33, 3), dtype=np.uint8)
    alpha = rng.random((45, 33)) < 0.8
    export._write_rgba_png(tmp_path / "a.png", on_disk(image), on_disk(alpha))
    want = np.dstack([image, np.where(alpha, 255, 0).astype(np.uint8)])
    with Image.open(tmp_path / "a.png") as im:
        assert im.mode == "RGBA" and np.array_equal(np.asarray(im), want)

"""The 3-D view: the model's JSON (the mesh thinned to ``ReportConfig.max_faces``, its
texture as a PNG data URI, a marker per defect, joint and lateral) written a piece at a time
into a scratch file, with the viewer (viewer.js) around it.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Iterator
from importlib import resources
from typing import IO, Any

import numpy as np

from omnipipe.memory import release_freed_memory
from omnipipe.report.encode import (
    PNG_URI_HEAD,
    RESIZE_DROP_S,
    base64_file_parts,
    number_chunks,
    png_file,
)
from omnipipe.report.inputs import ReportConfig, ReportInputs, clock_deg, point_features
from omnipipe.spill import drop_pages, dropping_pages, zeros_on_disk


def referenced_only(
    verts: np.ndarray, faces: np.ndarray, uvs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertices (N, 3) and uvs (N, 2) some face of ``faces`` (F, 3) uses, in their
    order, and the faces renumbered to them: the same triangles."""
    used = np.zeros(len(verts), bool)
    used[faces.ravel()] = True
    if used.all():
        return verts, faces, uvs
    new_id = np.cumsum(used) - 1
    return verts[used], new_id[faces].astype(faces.dtype), uvs[used]


def _model_json(inputs: ReportInputs, config: ReportConfig) -> str | None:
    """The 3-D view's JSON (:func:`_model_json_parts` joined), or None without a mesh."""
    parts = _model_json_parts(inputs, config)
    return None if parts is None else "".join(parts)


def _model_json_parts(inputs: ReportInputs, config: ReportConfig) -> Iterator[str] | None:
    """The 3-D view's JSON in pieces (the number lists a chunk of values at a time, so
    the page is written without holding it whole), or None without a mesh."""
    if inputs.mesh_vertices is None or inputs.mesh_faces is None or not len(inputs.mesh_faces):
        return None
    verts = np.asarray(inputs.mesh_vertices, float)
    faces = np.asarray(inputs.mesh_faces)
    uvs = inputs.mesh_uvs if inputs.mesh_uvs is not None else np.zeros((len(verts), 2))
    if len(faces) > config.max_faces:
        from omnipipe.report.thin import thin_mesh

        # Clustered on the texture's grid: the view's vertices and faces stay within
        # max_faces however long the run.
        shape = None if inputs.texture is None else np.asarray(inputs.texture).shape[:2]
        verts, faces, uvs = thin_mesh(verts, faces, uvs, config.max_faces, shape)
        release_freed_memory()  # the whole mesh's pages (omnipipe.spill) and temporaries
    # The mesh's vertex array is the run's whole point cloud: points no face uses (inside a
    # lateral's opening, a joint's gap, under water, an outlier) are left out of the view, so
    # they neither frame the camera nor reach the page.
    verts, faces, uvs = referenced_only(verts, faces, uvs)
    png = None  # the texture's PNG, its data URI's text written a piece at a time
    if inputs.texture is not None:
        import cv2

        tex = np.asarray(inputs.texture)
        scale = config.texture_max_px / max(tex.shape[:2])
        if scale < 1:
            # The atlas (omnipipe.spill) read whole in one call: its pages dropped as the
            # call goes, not only after it.
            # Made in the scratch too (cv2 writes into ``dst`` when its size is the one
            # it computes, else it returns a new array: the same values either way).
            h, w = tex.shape[:2]
            dst = zeros_on_disk((round(h * scale), round(w * scale), *tex.shape[2:]), tex.dtype)
            with dropping_pages(RESIZE_DROP_S):
                tex = cv2.resize(tex, None, dst=dst, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            drop_pages()  # the atlas's (omnipipe.spill): not under the PNG's encoding
        png = png_file(tex)
        del tex
        release_freed_memory()  # the atlas's pages
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    rest = {
        "markers": _markers(inputs),
        "texture": None if png is None else _TEXTURE_SLOT,
        "centre": ((lo + hi) / 2).tolist(),
        "radius": float(max(np.linalg.norm(hi - lo) / 2, 1.0)),
    }
    # WebGL samples textures with v = 0 at the first uploaded row (the image top).
    uv_rows = np.column_stack([uvs[:, 0], 1.0 - uvs[:, 1]])

    def parts() -> Iterator[str]:
        # The long arrays as JSON number lists in one %-format a chunk (5x faster than
        # lists of Python floats through json.dumps; the viewer reads the same values).
        for name, fmt, values in (("positions", "%.2f", verts), ("uvs", "%.5f", uv_rows), ("indices", "%d", faces)):
            yield f'{"{" if name == "positions" else ""}"{name}":['
            yield from number_chunks(fmt, values)
            yield "],"
        # Only the JSON part can hold "</" (the number lists and base64 cannot): escaped
        # alone. The texture's URI (JSON needs no escapes in it) goes in where its slot is.
        text = json.dumps(rest, separators=(",", ":"))[1:].replace("</", "<\\/")
        if png is None:
            yield text
            return
        head, tail = text.split(json.dumps(_TEXTURE_SLOT), 1)
        yield f'{head}"{PNG_URI_HEAD}'
        with png:
            yield from base64_file_parts(png)
        yield f'"{tail}'

    return parts()


_TEXTURE_SLOT = "\x00omnipipe-texture\x00"
"""Stands for the texture's data URI in the 3-D view's JSON until it is written out."""


def _markers(inputs: ReportInputs) -> list[dict[str, Any]]:
    """The 3-D view's labels: each defect's measured centre and each joint's and lateral's
    position (world, mm; a joint without an offset direction at 12:00)."""
    from omnipipe.report.views import centre_point, nearest_wall_point

    if inputs.wall is None or inputs.wall_points_in_world is None:
        return []
    out = []
    twelve = None
    for kind, axial, angle in point_features(inputs.summary):
        if angle is None:
            twelve = clock_deg(inputs) if twelve is None else twelve
        at = twelve if angle is None else angle
        # On the wall at the opening's rim or the joint, not on the branch behind it.
        p = nearest_wall_point(axial, at, inputs.wall, inputs.wall_points_in_world, on_wall_mm=2.0)
        if p is not None:
            out.append({"label": kind, "position": [round(float(v), 2) for v in p], "href": "#features"})
    for k, d in enumerate(inputs.defects):
        p = centre_point(d, inputs.wall, inputs.wall_points_in_world)
        if p is not None:
            out.append(
                {
                    "label": f"#{k + 1} {d.kind}" + (" (truncated)" if d.truncated else ""),
                    "position": [round(float(v), 2) for v in p],
                    "href": f"#defect-{k + 1}",
                }
            )
    return out


def model_view_file(inputs: ReportInputs, config: ReportConfig) -> IO[str]:
    """The 3-D view's HTML (:func:`_model_view_parts` of :func:`_model_json_parts`)
    written a piece at a time into an unnamed text file of the run's scratch
    (:func:`omnipipe.scratch.scratch_dir`; gone when closed), positioned at its start."""
    from omnipipe.scratch import scratch_dir

    fh = tempfile.TemporaryFile("w+", encoding="utf-8", newline="", prefix="omnipipe-view-", dir=scratch_dir())
    for part in _model_view_parts(_model_json_parts(inputs, config)):
        fh.write(part)
    fh.seek(0)
    return fh


def _model_view_parts(model: Iterator[str] | None) -> Iterator[str]:
    """The 3-D view in pieces: the model's JSON as its pieces come and the viewer
    (viewer.js), or a note without a mesh."""
    if model is None:
        yield "<p class='note'>No mesh was built.</p>"
        return
    viewer_js = resources.files("omnipipe.report").joinpath("viewer.js").read_text(encoding="utf-8")
    yield (
        "<div id='model-wrap'><canvas id='model-view'></canvas></div>"
        "<p id='model-status' class='note'>loading…</p>"
        "<script type='application/json' id='model-data'>"
    )
    yield from model
    yield f"</script><script>{viewer_js}</script>"

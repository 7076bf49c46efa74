"""Report stage: a self-contained report.html (opens offline, no CDN).

It holds an interactive 3-D view of the textured model (a small WebGL viewer shipped
with omnipipe), the inner diameter and ovality along the pipe, the unrolled wall
image with the defects outlined, the trajectory, the defect table, and the
measured-vs-true table (the paper's Table I) when ground truth exists.

The page is ``templates/report.html`` (a :class:`string.Template`: its style sheet,
headings and notes) filled with the sections made here. Printed (A4 or Letter,
whichever the printer uses) it has no 3-D view, keeps headings with what follows them
and never splits tables and figures across pages.
"""

from __future__ import annotations

import html
import json
import math
import tempfile
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from string import Template
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from omnipipe.memory import release_freed_memory
from omnipipe.report.bands import imshow_in_bands
from omnipipe.report.encode import (
    FIGURE_DPI,
    PNG_URI_HEAD,
    RESIZE_DROP_S,
    base64_file_parts,
    collected,
    figure_data_uri,
    number_chunks,
    png_data_uri,
    png_file,
    text_file_parts,
)
from omnipipe.report.inputs import (
    ReportConfig,
    ReportInputs,
    clock_deg,
    point_features,
    survey_of,
    travel_sign,
)
from omnipipe.spill import drop_pages, dropping_pages, zeros_on_disk

if TYPE_CHECKING:
    from collections.abc import Sequence

    from matplotlib.axes import Axes

    from omnipipe.contract import Defect, TrajectoryQuality
    from omnipipe.report.relief import WallPoints


def _plots(inputs: ReportInputs) -> dict[str, str]:
    """The figures (PNG data URIs) by name: profile, trajectory, unrolled."""
    import matplotlib

    matplotlib.use("Agg")
    out: dict[str, str] = {}
    if inputs.stations_axial_mm is not None and len(inputs.stations_axial_mm):
        out["profile"] = collected(_profile_plot(inputs))
    poses = np.asarray(inputs.world_from_rig)
    if poses.ndim == 3 and len(poses):
        out["trajectory"] = collected(_trajectory_plot(inputs, poses[:, :3, 3]))
    if inputs.unrolled is not None and inputs.unrolled_extent is not None:
        # Hatched and rolled to 12:00 in one pass (the report's one copy of the wall).
        w = min(np.asarray(inputs.unrolled).shape[1], UNROLLED_MAX_COLUMNS)
        shift, extent = _twelve_shift(w, inputs.unrolled_extent, clock_deg(inputs))
        shown = marked_unrolled(inputs.unrolled, inputs.unrolled_alpha, shift)
        out["unrolled"] = collected(_unrolled_plot(inputs, shown, extent))
        del shown
        release_freed_memory()  # the wall's pages (omnipipe.spill) not under the next plot
    if inputs.wall is not None and len(inputs.wall.axial_mm):
        out["relief"] = collected(_relief_plot(inputs, inputs.wall))
        release_freed_memory()
    return out


UNROLLED_MAX_COLUMNS = 1800
"""The report's unrolled wall is drawn from at most this many columns (area-averaged):
its figure is about 1000 px wide."""


_MARK_ROWS = 256
"""Rows of the unrolled wall :func:`marked_unrolled` hatches and rolls at a time."""


def marked_unrolled(image: np.ndarray, alpha: np.ndarray | None, roll: int = 0) -> np.ndarray:
    """(h, w, 3) uint8 unrolled wall for the report: at most
    :data:`UNROLLED_MAX_COLUMNS` columns (rows scaled alike), and the cells that are not
    wall (``alpha`` False: a gap, an opening, unseen) hatched in two greys, so that no
    missing wall passes for dark wall and nothing is smeared into it; then its columns
    rolled ``roll`` to the left (:func:`_from_twelve`). A new array (the caller's image
    is never drawn on), made a band of :data:`_MARK_ROWS` rows at a time: one copy of
    the wall, not three."""
    import cv2

    h, w = image.shape[:2]
    rgb = image[..., :3]
    seen = None if alpha is None else np.asarray(alpha, bool)
    out = None
    if w > UNROLLED_MAX_COLUMNS:
        f = UNROLLED_MAX_COLUMNS / w
        size = (UNROLLED_MAX_COLUMNS, max(1, round(h * f)))
        rgb = out = cv2.resize(np.ascontiguousarray(rgb), size, interpolation=cv2.INTER_AREA)
        if seen is not None:
            # A shown cell is wall when most of the cells it averages are.
            seen = cv2.resize(seen.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5
    if out is None:  # in the run's scratch (omnipipe.spill): a band resident at a time
        out = zeros_on_disk((h, w, 3), np.uint8)
    for r0 in range(0, rgb.shape[0], _MARK_ROWS):
        r1 = min(r0 + _MARK_ROWS, rgb.shape[0])
        band = np.array(rgb[r0:r1])
        if seen is not None and not seen[r0:r1].all():
            rr, cc = np.nonzero(~seen[r0:r1])
            band[rr, cc] = np.where((((rr + r0 + cc) // 4) % 2)[:, None] == 0, 170, 110).astype(np.uint8)
        out[r0:r1] = np.roll(band, -roll, axis=1) if roll else band
        drop_pages()
    return out


def _twelve_shift(
    w: int, extent: tuple[float, float, float, float], twelve_deg: float
) -> tuple[int, tuple[float, float, float, float]]:
    """The columns to roll a full-turn unrolled image ``w`` columns wide left so that its
    column nearest 12:00 (omnipipe angle ``twelve_deg``) is the left edge, and its new
    extent."""
    a0, a1, s0, s1 = extent
    per_col = (a1 - a0) / w
    shift = int(round(((twelve_deg - a0) % 360.0) / per_col)) % w
    return shift, (a0 + shift * per_col, a1 + shift * per_col, s0, s1)


def _from_twelve(
    image: np.ndarray, extent: tuple[float, float, float, float], twelve_deg: float
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The full-turn unrolled image with its columns rolled so that the column nearest
    12:00 (omnipipe angle ``twelve_deg``) is the left edge, and its new extent: the
    texture reads like the deviation map (12:00 to 12:00, clockwise)."""
    shift, rolled = _twelve_shift(image.shape[1], extent, twelve_deg)
    return np.roll(image, -shift, axis=1), rolled


def _relief_plot(inputs: ReportInputs, wall: WallPoints) -> str:
    """The unrolled wall's deviation map (mm, colour scale) with the defects outlined."""
    import matplotlib.pyplot as plt

    from omnipipe.report import relief

    z0, z1 = float(np.min(wall.axial_mm)), float(np.max(wall.axial_mm))
    ref = clock_deg(inputs)
    a0 = ref  # 12:00 at the left edge: columns run clockwise through a full turn
    cell = max(1.0, (z1 - z0) / 400.0)
    grid = relief.deviation_grid(wall, (z0, z1), (a0, a0 + 360.0), cell)
    drop_pages()  # every wall point was read (omnipipe.spill): not under the figure
    circ = 2 * math.pi * wall.radius_mm
    fig, ax = plt.subplots(figsize=(9, min(12.0, 9 * (z1 - z0) / circ + 1.2)))
    vmax = relief.relief_vmax([d.height_mm for d in inputs.defects], inputs.summary.get("wall_noise_mm"))
    im = relief.draw_relief(ax, grid, (a0, a0 + 360.0, z0, z1), vmax)
    for k, d in enumerate(inputs.defects):
        shifted = _shift_angle(d, a0)
        relief.outline(ax, shifted, wall.radius_mm)
        ax.text(shifted.angle_deg, shifted.axial_start_mm, f" #{k + 1}", fontsize=8, va="bottom")
    relief.clock_ticks(ax, a0, a0 + 360.0, ref)
    ax.set_xlabel("clock position (looking in the direction of travel)")
    _distance_axis(ax, inputs)
    fig.colorbar(im, ax=ax, label="deviation from the wall (mm): − bulge, + dent", shrink=0.8)
    return figure_data_uri(fig)


def _distance_axis(ax: Axes, inputs: ReportInputs) -> None:
    """The vertical axis in the inspector's distance (m from the start node or the first
    measured ring)."""
    from omnipipe.report.deliverable import distance_origin
    from omnipipe.report.relief import distance_axis

    origin = distance_origin(inputs.summary, survey_of(inputs.summary))
    distance_axis(ax, origin.offset_m, origin.name)


def _shift_angle(d: Defect, a0: float) -> Defect:
    """``d`` with its angle moved into [a0, a0 + 360)."""
    from dataclasses import replace

    return replace(d, angle_deg=a0 + (d.angle_deg - a0) % 360.0)


def _defect_relief(inputs: ReportInputs, d: Defect, k: int) -> str:
    """One defect's relief map crop (mm colour scale, outline, clock axis) as a data URI."""
    import matplotlib.pyplot as plt

    from omnipipe.report import relief

    wall = inputs.wall
    if wall is None:
        return ""
    a0, a1, z0, z1 = relief.defect_window(d, wall.radius_mm)
    cell = max(0.25, min(2.0, min(d.width_mm, d.length_mm) / 12.0))
    grid = relief.deviation_grid(wall, (z0, z1), (a0, a1), cell)
    drop_pages()  # every wall point was read (omnipipe.spill): not under the figure
    fig, ax = plt.subplots(figsize=(3.2, 3.2))
    vmax = relief.relief_vmax([d.height_mm], inputs.summary.get("wall_noise_mm"))
    im = relief.draw_relief(ax, grid, (a0, a1, z0, z1), vmax)
    relief.outline(ax, d, wall.radius_mm)
    span_h = (a1 - a0) / 30.0
    relief.clock_ticks(ax, a0, a1, clock_deg(inputs), step_h=0.25 if span_h < 2 else 0.5 if span_h < 4 else 1.0)
    ax.set_xlabel("clock", fontsize=9)
    _distance_axis(ax, inputs)
    ax.set_ylabel("distance (m)", fontsize=9)  # from where: the card's heading says
    ax.tick_params(labelsize=8)
    ax.set_title(f"#{k + 1} {d.kind}" + (" (truncated)" if d.truncated else ""), fontsize=10)
    bar = fig.colorbar(im, ax=ax, shrink=0.85)
    bar.set_label("deviation (mm)", fontsize=9)
    bar.ax.tick_params(labelsize=8)
    return figure_data_uri(fig)


def _profile_plot(inputs: ReportInputs) -> str:
    """Diameter (with 2-sigma bars) and ovality along the pipe."""
    import matplotlib.pyplot as plt

    fig, ax1 = plt.subplots(figsize=(8, 3.2))
    sig = [st.get("inner_diameter_sigma_mm") for st in inputs.summary.get("stations", [])]
    axial = np.asarray(inputs.stations_axial_mm)
    if len(sig) == len(axial) and all(v is not None for v in sig):
        ax1.errorbar(
            axial,
            inputs.stations_diameter_mm,
            yerr=2 * np.asarray(sig, float),
            fmt="o-",
            color="#1f77b4",
            ms=3,
            capsize=2,
            label="diameter ± 2 sigma",
        )
    else:
        ax1.plot(axial, inputs.stations_diameter_mm, "o-", color="#1f77b4", ms=3)
    survey = inputs.summary.get("survey") or {}
    ax1.set_xlabel("axial position (mm, from the first frame's mirror focus)")
    from omnipipe.report.deliverable import distance_origin

    # A second axis: the inspector's distance (from the start node or the first ring), m.
    origin = distance_origin(inputs.summary, survey_of(inputs.summary))
    off = origin.offset_m
    top = ax1.secondary_xaxis("top", functions=(lambda x: off + x / 1000.0, lambda m: (m - off) * 1000.0))
    top.set_xlabel(f"distance (m) from the {origin.name}")
    nominal = survey.get("nominal_diameter_mm")
    if nominal:
        ax1.axhline(nominal, color="#888", ls="--", lw=1, label="nominal")
    ax1.set_ylabel("inner diameter (mm)", color="#1f77b4")
    if inputs.stations_ovality is not None:
        ax2 = ax1.twinx()
        ax2.plot(axial, 100 * np.asarray(inputs.stations_ovality), "s-", color="#d62728", ms=3)
        ax2.set_ylabel("ovality (%)", color="#d62728")
    ax1.grid(alpha=0.3)
    return figure_data_uri(fig)


def _trajectory_plot(inputs: ReportInputs, p: np.ndarray) -> str:
    """Top and side view of the (N, 3) rig positions ``p`` (mm), unreliable frames red."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    bad = _unreliable_frames(inputs)
    for ax, (i, j, name) in zip(axes, ((2, 0, "top view: x"), (2, 1, "side view: y")), strict=True):
        ax.plot(p[:, i], p[:, j], ".-", ms=3)
        for n, (lo, hi) in enumerate(bad):
            sel = (inputs.frame_index >= lo) & (inputs.frame_index <= hi)
            ax.plot(
                p[sel, i], p[sel, j], "o", ms=4, color="#d62728",
                label="unreliable motion" if n == 0 else None,
            )
        if bad:
            ax.legend(fontsize=7)
        ax.set_xlabel("z: along the first rig axis (mm)")
        ax.set_ylabel(f"{name} (mm)")
        ax.grid(alpha=0.3)
    fig.suptitle("estimated rig trajectory (world = first rig frame)")
    return figure_data_uri(fig)


_LABEL_BOX = {"boxstyle": "round,pad=0.15", "fc": "black", "alpha": 0.55, "lw": 0}
"""A feature label's backing on the unrolled wall (readable on bright wall and on hatch)."""


def _unrolled_plot(
    inputs: ReportInputs, image: np.ndarray, extent: tuple[float, float, float, float]
) -> str:
    """The unrolled wall with the defects outlined and the unreliable stretches shaded."""
    import matplotlib.patches
    import matplotlib.pyplot as plt

    a0, a1, s0, s1 = extent
    # At most 12 inches tall, as the relief map: a longer run's figure (and the image
    # matplotlib resamples into it) no longer grows with the run.
    height = min(12.0, 9 * (s1 - s0) / max(1.0, (a1 - a0) * (inputs.radius_mm or 100) * math.pi / 180) + 1)
    fig, ax = plt.subplots(figsize=(9, height))
    # Area-averaged to at most the figure's pixels first: matplotlib's resampling costs
    # about 40 bytes a pixel of the image it is given (60 MB for 3,000 frames' wall).
    rows, cols = (int(round(v * FIGURE_DPI)) for v in (height, 9.0))
    if image.shape[0] > rows or image.shape[1] > cols:
        import cv2

        size = (min(cols, image.shape[1]), min(rows, image.shape[0]))
        with dropping_pages(RESIZE_DROP_S):  # the whole wall read in one call
            image = cv2.resize(np.ascontiguousarray(image), size, interpolation=cv2.INTER_AREA)
        drop_pages()  # the whole wall's (omnipipe.spill): not under the drawing
    imshow_in_bands(ax, image, (a0, a1, s1, s0))
    radius = inputs.radius_mm or 100.0
    for k, defect in enumerate(inputs.defects):
        d = _shift_angle(defect, a0)  # drawn within the image's turn
        half_w = math.degrees(0.5 * d.width_mm / radius)
        rect = matplotlib.patches.Rectangle(
            (d.angle_deg - half_w, d.axial_start_mm),
            2 * half_w,
            d.length_mm,
            fill=False,
            ec="cyan" if d.kind == "bulge" else "yellow",
            lw=1.5,
        )
        ax.add_patch(rect)
        rect.set_linestyle("--" if d.truncated else "-")
        ax.text(d.angle_deg + half_w + 2, d.axial_start_mm, f"#{k + 1} {d.kind}", color="white", fontsize=8)
    for kind, axial, angle in point_features(inputs.summary):
        if angle is None:  # a joint all round: a line across the wall
            ax.axhline(axial, color="white", lw=0.8, ls=":")
            ax.text(a1 - 2, axial, kind, color="white", fontsize=7, ha="right", va="bottom", bbox=_LABEL_BOX)
        else:
            x = a0 + (angle - a0) % 360.0
            ax.plot([x], [axial], marker="+", color="white", ms=9, mew=1.2)
            ax.text(x + 3, axial, kind, color="white", fontsize=8, va="center", bbox=_LABEL_BOX)
    quality = inputs.trajectory_quality
    for u in () if quality is None else quality.unreliable:
        if u.axial_start_mm is not None and u.axial_end_mm is not None:
            ax.axhspan(u.axial_start_mm, u.axial_end_mm, color="#d62728", alpha=0.3, lw=0)
            ax.text(a0 + 2, u.axial_start_mm, "unreliable motion", color="white", fontsize=7, va="top")
    from omnipipe.report.relief import clock_ticks

    clock_ticks(ax, a0, a1, clock_deg(inputs))
    ax.set_xlabel("clock position (looking in the direction of travel)")
    _distance_axis(ax, inputs)
    return figure_data_uri(fig)


def _unreliable_frames(inputs: ReportInputs) -> list[tuple[int, int]]:
    """(first, last) frame of each unreliable stretch, when poses carry frame indices."""
    if inputs.frame_index is None or inputs.trajectory_quality is None:
        return []
    return [(u.first_frame, u.last_frame) for u in inputs.trajectory_quality.unreliable]


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


def value_pm(value: float | None, sigma: float | None, *, plain: str = "±", digits: int = 2) -> str:
    """``value ± sigma`` with as many decimals as the sigma needs (at least ``digits``
    when it is large, 3 when it is under 0.1); "-" without a value, the value alone
    without a sigma."""
    if value is None or not isinstance(value, int | float) or not math.isfinite(value):
        return "-"
    if sigma is None or not isinstance(sigma, int | float) or not math.isfinite(sigma):
        return f"{round(value, digits) + 0.0:.{digits}f}"  # (+ 0.0: never "-0.00")
    nd = max(digits, 3 if sigma < 0.1 else 2) if sigma < 1 else max(1, digits - 1)
    return f"{round(value, nd) + 0.0:.{nd}f} {plain} {sigma:.{nd}f}"


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return html.escape(str(value))


_SURVEY_LABELS = (
    ("site", "site"),
    ("asset_id", "asset ID"),
    ("pipe_material", "pipe material"),
    ("nominal_diameter_mm", "nominal diameter (mm)"),
    ("start_node", "start node"),
    ("end_node", "end node"),
    ("direction", "direction"),
    ("start_offset_m", "start node to first frame (m)"),
    ("operator", "operator"),
    ("date", "date"),
)


def _survey_html(survey: dict[str, Any] | None) -> str:
    """The survey header (survey.yaml) as a two-column table, or '' without one."""
    if not survey:
        return ""
    rows = [
        f"<tr><td>{label}</td><td>{_fmt(survey.get(key))}</td></tr>"
        for key, label in _SURVEY_LABELS
        if survey.get(key) is not None
    ]
    return "<h2>Survey</h2><table class='survey'>" + "".join(rows) + "</table>" if rows else ""


def _defect_extras(inputs: ReportInputs) -> tuple[list[list[str]], list[str]]:
    """Per defect: the table's cells (clock, distance, grade, link to its views) and its
    views' card (relief map, wall texture, camera view; each enlarges when clicked)."""
    from omnipipe.report.deliverable import defect_rows

    rows = defect_rows(inputs.defects, inputs.summary, survey_of(inputs.summary), travel_sign(inputs))
    cells, cards = [], []
    for k, row in enumerate(rows):
        v = row.values
        views = _defect_views_html(inputs, row.defect, k)
        sig = v["clock_sigma_deg"]
        end_sig = v["distance_end_sigma_m"]
        cells.append(
            [
                f"{v['clock']}" + (f" ± {sig}°" if sig else ""),
                f"{v['distance_start_m']} – {v['distance_end_m']}" + (f" ± {end_sig}" if end_sig else ""),
                v["severity_grade"],
                f"<a href='#views-{k + 1}'>views</a>" if views else "",
            ]
        )
        if views:
            d = row.defect
            head = (
                f"#{k + 1} {html.escape(d.kind)} at {v['clock']}, {v['distance_start_m']} – "
                f"{v['distance_end_m']} m from the {html.escape(v['distance_from'])}: "
                f"{'≥ ' if d.truncated else ''}{d.height_mm:.2f} mm high"
                + (" <span class='warn'>(truncated: runs past the measured stretch)</span>" if d.truncated else "")
            )
            cards.append(f"<div class='card keep' id='views-{k + 1}'><h3>{head}</h3>{''.join(views)}</div>")
    return cells, cards


def _defect_views_html(inputs: ReportInputs, d: Defect, k: int) -> list[str]:
    """The ``<figure>`` of each view of defect ``d`` (number ``k + 1``)."""
    views = []
    if inputs.wall is not None:
        views.append(
            _figure_html(collected(_defect_relief(inputs, d, k)), "relief map: deviation from the fitted wall (mm)")
        )
    if inputs.unrolled is not None and inputs.unrolled_extent is not None and inputs.radius_mm:
        from omnipipe.report.deliverable import crop_unrolled

        ext = inputs.unrolled_extent
        crop = crop_unrolled(
            inputs.unrolled, inputs.unrolled_alpha, ext[2], (ext[3] - ext[2]) / inputs.unrolled.shape[0], d,
            2 * math.pi * inputs.radius_mm,
        )
        views.append(_figure_html(png_data_uri(crop), "wall texture (unrolled)"))
    view = inputs.defect_views[k] if k < len(inputs.defect_views) else None
    if view is not None:
        views.append(_figure_html(png_data_uri(view.image), f"camera view, frame {view.frame}"))
    return views


def _figure_html(uri: str, caption: str) -> str:
    return f"<figure>{_zoomable(uri, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>"


def _zoomable(uri: str, alt: str) -> str:
    """An image that opens large when clicked (the page's zoom overlay)."""
    return f"<img class='crop zoomable' alt='{html.escape(alt)}' title='click to enlarge' src='{uri}'>"


def render_html(inputs: ReportInputs, config: ReportConfig | None = None) -> str:
    """The report page as one self-contained HTML string (``templates/report.html``)."""
    return "".join(_page_parts(inputs, config or ReportConfig()))


_MODEL_SLOT = "\x00omnipipe-model-view\x00"
"""Stands for the 3-D view in the filled template until the page is written out."""


def _page_parts(inputs: ReportInputs, config: ReportConfig) -> Iterator[str]:
    """The report page in pieces: the template filled in, with the 3-D view's JSON
    (the page's longest part) written a chunk at a time into it."""
    s = inputs.summary
    # The 3-D view first, into the run's scratch: the mesh's thinning and the texture's
    # PNG (a long run's largest temporaries here) not on top of what drawing the figures
    # leaves resident (matplotlib, its fonts and caches).
    view = _model_view_file(inputs, config)
    release_freed_memory()
    plots = _plots(inputs)
    template = resources.files("omnipipe.report").joinpath("templates", "report.html")
    page = Template(template.read_text(encoding="utf-8"))
    filled = page.substitute(
        title=html.escape(config.title),
        survey=_survey_html(s.get("survey")),
        summary_rows=_summary_rows(s) + _motion_rows(s, inputs.trajectory_quality) + _calibration_row(s),
        warnings="".join(f"<p class='warn'>warning: {html.escape(str(w))}</p>" for w in s.get("warnings", [])),
        truth=_truth_table(inputs.truth),
        trajectory_note=_trajectory_note(inputs.evaluation),
        model_view=_MODEL_SLOT,
        defects=_defects_section(inputs) + _features_section(s, travel_sign(inputs)),
        figures=_figures(
            plots, inputs.unrolled_alpha is not None and not np.asarray(inputs.unrolled_alpha).all()
        ),
        files=_files_table(s.get("files")),
    )
    del plots
    release_freed_memory()  # the defects' relief maps read every wall point
    before, after = filled.split(_MODEL_SLOT, 1)
    del filled
    yield before
    del before
    yield from text_file_parts(view)
    yield after


def _model_view_file(inputs: ReportInputs, config: ReportConfig) -> IO[str]:
    """The 3-D view's HTML (:func:`_model_view_parts` of :func:`_model_json_parts`)
    written a piece at a time into an unnamed text file of the run's scratch
    (:func:`omnipipe.scratch.scratch_dir`; gone when closed), positioned at its start."""
    from omnipipe.scratch import scratch_dir

    fh = tempfile.TemporaryFile("w+", encoding="utf-8", newline="", prefix="omnipipe-view-", dir=scratch_dir())
    for part in _model_view_parts(_model_json_parts(inputs, config)):
        fh.write(part)
    fh.seek(0)
    return fh


def _summary_rows(s: dict[str, Any]) -> str:
    """The summary table's rows of the measurements and the processing time."""
    rows = [
        f"<tr><td>frames</td><td>{_fmt(s.get('frames'))}</td></tr>",
        f"<tr><td>frames registered</td><td>{_fmt(s.get('frames_registered'))}</td></tr>",
        "<tr><td>inner diameter</td><td>"
        f"{value_pm(s.get('inner_diameter_mm'), s.get('inner_diameter_sigma_mm'))} mm</td></tr>",
    ]
    if s.get("run_length_mm") is not None:
        rows.append(
            "<tr><td>measured length of pipe</td><td>"
            f"{value_pm(s['run_length_mm'], s.get('run_length_sigma_mm'), digits=1)} mm</td></tr>"
        )
    if s.get("detection_limit_mm") is not None:
        ref = s.get("detection_limit_reference_mm") or {}
        size = (
            f" (smallest height reported; a defect {ref['width']:g} mm wide and {ref['length']:g} mm "
            "long this high rises above the detector's threshold with 95 % probability)"
            if ref.get("width") and ref.get("length")
            else ""
        )
        rows.append(
            f"<tr><td>detection limit</td><td>{_fmt(s['detection_limit_mm'])} mm high{size}</td></tr>"
        )
    if s.get("wall_noise_mm") is not None:
        rows.append(f"<tr><td>wall noise (1 sigma)</td><td>{_fmt(s['wall_noise_mm'], 3)} mm</td></tr>")
    if s.get("ovality_max") is not None:
        rows.append(f"<tr><td>largest ovality</td><td>{_fmt(100 * s['ovality_max'])} %</td></tr>")
    if s.get("timings_s"):
        t = s["timings_s"]
        rows.append(
            "<tr><td>processing time</td><td>"
            + ", ".join(f"{k} {v:.1f} s" for k, v in t.items())
            + "</td></tr>"
        )
    return "".join(rows)


def _motion_rows(s: dict[str, Any], q: TrajectoryQuality | None) -> str:
    """The summary table's rows of the camera motion check and the metric scale."""
    if q is None:
        return ""
    bad = q.unreliable
    steps = max(int(s.get("frames") or 1) - 1, 0)
    verdict = (
        f"<span class='warn'>UNRELIABLE in {len(bad)} stretch(es): frames "
        + ", ".join(f"{u.first_frame}-{u.last_frame}" for u in bad)
        + " (marked red on the unrolled wall and the trajectory)</span>"
        if bad
        else "every moving step confirmed by two scale sources"
    )
    rows = [
        f"<tr><td>camera motion check</td><td>{_fmt(q.steps_checked)} of {steps} frame "
        f"steps verified; {verdict}</td></tr>"
    ]
    if q.scale_source:
        gap, sigma = q.wall_scale_gap_pct, q.scale_sigma_pct
        rows.append(
            f"<tr><td>metric scale</td><td>{html.escape(str(q.scale_source))}"
            + (f"; 1-sigma {sigma:.2f} % of every length along the pipe" if sigma is not None else "")
            + (f"; wall vs laser before combining {gap:+.2f} %" if gap is not None else "")
            + "</td></tr>"
        )
    return "".join(rows)


def _calibration_row(s: dict[str, Any]) -> str:
    """The summary table's row of the rig calibration's share of the uncertainties."""
    cal = s.get("calibration_sigma_rel")
    return (
        "<tr><td>rig calibration</td><td>"
        + (
            f"1-sigma {100 * cal:.3f} % of every length (rig.yaml laser.offset_sigma_mm), "
            "included in every uncertainty"
            if cal
            else "rig.yaml states no calibration uncertainty: the uncertainties above exclude it"
        )
        + "</td></tr>"
    )


def _truth_table(truth: Sequence[tuple[Any, ...]] | None) -> str:
    """The measured-vs-true table (the paper's Table I), or '' without ground truth."""
    if not truth:
        return ""
    parts = [
        "<h2>Measured vs true (the paper's Table I)</h2><table><tr><th></th>"
        "<th>measured ± 1 sigma</th><th>true</th><th>error</th><th>error / sigma</th></tr>"
    ]
    for row in truth:
        name, meas, sig, true, unit = row if len(row) == 5 else (row[0], row[1], None, *row[2:])
        err = None if meas is None or true is None else meas - true
        z = "" if err is None or not sig else f"{err / sig:+.1f}"
        parts.append(
            f"<tr><td>{html.escape(name)}</td><td>{value_pm(meas, sig)} {unit}</td>"
            f"<td>{_fmt(true)} {unit}</td>"
            f"<td>{'' if err is None else f'{err:+.2f} {unit}'}</td><td>{z}</td></tr>"
        )
    parts.append("</table>")
    return "".join(parts)


def _trajectory_note(ev: dict[str, Any] | None) -> str:
    """The trajectory's errors against ground truth, or ''."""
    if not ev or not ev.get("trajectory"):
        return ""
    tr = ev["trajectory"]
    return (
        "<p class='note'>Trajectory against ground truth: ATE "
        f"{tr['ate_rmse_mm']:.3f} mm RMS, scale error {tr['scale_error_percent']:.3f} %, rotation "
        f"{tr['rotation_rmse_deg']:.3f} deg RMS over {tr['path_length_mm']:.0f} mm.</p>"
    )


def _model_view(model: str | None) -> str:
    """The 3-D view: the model's JSON and the viewer (viewer.js), or a note without a mesh."""
    return "".join(_model_view_parts(None if model is None else iter([model])))


def _model_view_parts(model: Iterator[str] | None) -> Iterator[str]:
    """:func:`_model_view` in pieces, the model's JSON as its pieces come."""
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


_DEFECT_COLUMNS = (
    "<table><thead><tr><th>#</th><th>kind</th><th>height (mm)</th><th>width (mm)</th><th>length (mm)</th>"
    "<th>clock</th><th>distance (m)</th>"
    "<th>grade</th><th>views</th></tr></thead>"
)


def _feature_cells(f: dict[str, Any], reference_deg: float, offset_m: float) -> tuple[str, str, str]:
    """(distance, clock, sizes) cells of one report.json feature, in the defect table's
    conventions (metres from the distance origin, clock positions); each value with its
    sigma."""
    from omnipipe.report.deliverable import clock_position

    def pm(key: str) -> str:
        sig = f.get(key.replace("_mm", "_sigma_mm").replace("_deg", "_sigma_deg") if key != "percent" else "percent_sigma")
        return value_pm(f[key], sig, digits=2)

    def metres(key: str) -> str:
        sig = f.get(key.replace("_mm", "_sigma_mm"))
        return value_pm(offset_m + float(f[key]) / 1000.0, None if sig is None else float(sig) / 1000.0, digits=4)

    if f.get("axial_mm") is not None:
        where = metres("axial_mm") + " m"
    else:
        where = f"{metres('axial_from_mm')} – {metres('axial_to_mm')} m" + (" (truncated)" if f.get("truncated") else "")
    if f.get("motion_unreliable"):
        where += " (on unreliable camera motion)"
    angle_key = "angle_deg"
    if f.get("kind") == "joint":  # a joint's clock: its offset's direction, when significant
        off, osig = f.get("offset_mm") or 0.0, f.get("offset_sigma_mm") or 0.0
        angle_key = "offset_angle_deg" if off > 2.0 * osig else ""
    clock = ""
    if angle_key and isinstance(f.get(angle_key), int | float):
        clock = clock_position(float(f[angle_key]), reference_deg)[0]
        sig = f.get(angle_key.replace("_deg", "_sigma_deg"))
        clock += "" if sig is None else f" ± {float(sig):.1f}°"
    skip = {"kind", "axial_mm", "axial_from_mm", "axial_to_mm", "truncated", "points", "angle_deg", "offset_angle_deg"}
    sizes = [
        f"{k} {pm(k)}" for k, v in f.items()
        if k not in skip and "_sigma" not in k and isinstance(v, (int, float)) and not isinstance(v, bool)
    ]
    return html.escape(where), html.escape(clock), html.escape(", ".join(sizes))


def _features_section(s: dict[str, Any], travel_along_rig_z: float = 1.0) -> str:
    """The features' table (report.json ``features``: joints, laterals, bends, tapers,
    ovality and water stretches; features.csv codes them): distances and clock positions
    as the defect table's."""
    from omnipipe.report.deliverable import distance_origin, run_clock

    feats = s.get("features") or []
    if not feats:
        return ""
    survey = survey_of(s)
    reference = run_clock(s, survey, travel_along_rig_z).angle_deg
    origin = distance_origin(s, survey)
    rows = "".join(
        f"<tr><td>{html.escape(str(f.get('kind')))}</td><td>{a}</td><td>{b}</td><td>{c}</td></tr>"
        for f in feats
        for a, b, c in [_feature_cells(f, reference, origin.offset_m)]
    )
    return (
        "<h3 id='features'>Features (parts of the pipe, not defects)</h3>"
        f"<table><tr><th>kind</th><th>distance (m) from the {html.escape(origin.name)}</th>"
        f"<th>clock</th><th>sizes (± 1 sigma)</th></tr>{rows}</table>"
    )


def _defects_section(inputs: ReportInputs) -> str:
    """The defect table and its note, or the sentence that none was found."""
    s = inputs.summary
    if not inputs.defects:
        limit = s.get("detection_limit_mm")
        return (
            "<p>No bulges or dents"
            + ("" if limit is None else f" {_fmt(limit)} mm high or more")
            + " were found.</p>"
        )
    extra, cards = _defect_extras(inputs)
    parts = [_DEFECT_COLUMNS]
    for k, d in enumerate(inputs.defects):
        cells = [
            value_pm(value, sigma, digits=nd)
            for value, sigma, nd in (
                (d.height_mm, d.height_sigma_mm, 2),
                (d.width_mm, d.width_sigma_mm, 2),
                (d.length_mm, d.length_sigma_mm, 2),
            )
        ]
        if d.truncated:
            cells = ["≥ " + c for c in cells]
        kind = html.escape(d.kind) + (
            " <span class='warn'>(across unreliable motion)</span>" if d.motion_unreliable else ""
        ) + (
            " <span class='warn'>TRUNCATED: runs past the measured stretch; sizes are lower bounds</span>"
            if d.truncated
            else ""
        )
        cells += extra[k] if k < len(extra) else ["", "", "", ""]
        parts.append(
            f"<tr id='defect-{k + 1}'><td>{k + 1}</td><td>{kind}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"
        )
    parts.append("</table>")
    from omnipipe.report.deliverable import distance_origin, run_clock

    clock = run_clock(s, survey_of(s), travel_sign(inputs))
    origin = distance_origin(s, survey_of(s))
    parts.append(
        "<p class='note'>clock: looking in the direction of travel, clockwise; 12:00 = "
        + (
            f"the top of the pipe ({html.escape(clock.source)})"
            if clock.gravity
            else "<span class='warn'>clock from image up: no gravity reference</span> (the first "
            "frame's image up; give survey.yaml clock_reference_deg or imu.txt)"
        )
        + f". distance: metres along the pipe from the {html.escape(origin.name)} to the defect's "
        "start and end (± 1 sigma of the end). grade: height as % "
        "of the inner diameter, omnipipe's bands (docs/inspection_coding.md), not an official "
        "PACP / EN 13508-2 grade. views: the relief map (deviation from the fitted wall, mm; blue "
        "into the pipe), the wall texture around the defect and the camera's own view (a "
        "perspective crop of the frame that sees it closest, defects.csv best_view_frame), its "
        "half-height extent outlined (dashed: truncated); click a view to enlarge it. "
        "report.json keeps the angle in degrees "
        "from the first rig frame's x axis (angle_deg).</p>"
    )
    if cards:
        parts.append("<h2>Defect views</h2>" + "".join(cards))
    return "".join(parts)


def _figures(plots: dict[str, str], holes: bool = False) -> str:
    """The unrolled wall, the diameter profile and the trajectory (those drawn); ``holes``:
    the unrolled wall has cells with no wall (hatched, and said so)."""
    parts = []
    if "unrolled" in plots or "relief" in plots:
        parts.append("<h2>Unrolled wall</h2>")
        if "unrolled" in plots and "relief" in plots:
            parts.append(
                "<p class='screen-only'><label><input type='radio' name='wallmode' checked "
                "onclick=\"wallMode('texture')\"> texture</label> <label><input type='radio' "
                "name='wallmode' onclick=\"wallMode('relief')\"> deviation map (mm)</label></p>"
            )
        if "unrolled" in plots:
            parts.append(f"<img id='unrolled' class='zoomable' alt='unrolled wall' src='{plots['unrolled']}'>")
            if holes:
                parts.append(
                    "<p class='note'>Hatched grey: no wall there (a joint's gap, a lateral's opening, "
                    "or wall no frame saw); nothing is painted into it.</p>"
                )
        if "relief" in plots:
            hidden = " style='display:none'" if "unrolled" in plots else ""
            parts.append(
                f"<img id='relief' class='zoomable' alt='deviation map'{hidden} src='{plots['relief']}'>"
            )
    if "profile" in plots:
        parts.append(
            "<h2>Diameter and ovality along the pipe</h2>"
            f"<img id='profile' alt='diameter profile' src='{plots['profile']}'>"
        )
    if "trajectory" in plots:
        parts.append(
            f"<h2>Trajectory</h2><img id='trajectory' alt='trajectory' src='{plots['trajectory']}'>"
        )
    return "".join(parts)


def _files_table(files: dict[str, dict[str, Any]] | None) -> str:
    """Each 3-D file's unit and axes (report.json ``files``), or ''."""
    if not files:
        return ""
    return (
        "<h2>Files</h2><table><thead><tr><th>file</th><th>unit</th><th>axes</th>"
        "<th>stated in the file</th></tr></thead>"
        + "".join(
            "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in (n, *f.values())) + "</tr>"
            for n, f in files.items()
        )
        + "</table>"
    )


def run(config: ReportConfig, inputs: ReportInputs, out_path: Path) -> Path:
    """Write report.html to ``out_path`` and return it (a piece at a time: the page is
    not held whole)."""
    out_path = Path(out_path)
    with out_path.open("w", encoding="utf-8") as fh:
        for part in _page_parts(inputs, config):
            fh.write(part)
    return out_path

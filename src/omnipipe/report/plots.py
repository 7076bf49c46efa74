"""The report's figures as PNG data URIs (matplotlib, Agg): the diameter and ovality
profile, the trajectory, the unrolled wall (hatched where there is no wall, rolled to start
at 12:00, the defects, features and unreliable stretches marked) and the deviation (relief)
maps of the whole wall and of each defect.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.memory import release_freed_memory
from omnipipe.report.bands import imshow_in_bands
from omnipipe.report.encode import FIGURE_DPI, RESIZE_DROP_S, collected, figure_data_uri
from omnipipe.report.inputs import ReportInputs, clock_deg, point_features, survey_of
from omnipipe.spill import drop_pages, dropping_pages, zeros_on_disk

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from omnipipe.contract import Defect
    from omnipipe.report.relief import WallPoints


def draw_plots(inputs: ReportInputs) -> dict[str, str]:
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


def defect_relief(inputs: ReportInputs, d: Defect, k: int) -> str:
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

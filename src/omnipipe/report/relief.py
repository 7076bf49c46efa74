"""The wall's relief for a person: deviation maps in mm with a colour scale and clock axes.

The deviation of a wall point is its radial distance from the fitted wall (mm; negative:
a bulge into the pipe, positive: a dent). :func:`deviation_grid` bins the measured points
(axial position, angle, deviation) into a regular grid and fills the rows between rings
(linear along the pipe, only across gaps no wider than ``max_gap_mm``: an unmeasured
stretch stays blank). The figures put clock positions (``hh:mm``, 12:00 by the run's
:class:`~omnipipe.report.clock.ClockReference`) on the horizontal axis and the distance
along the pipe on the vertical one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.report.bands import imshow_in_bands
from omnipipe.spill import drop_pages

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from omnipipe.contract import Defect


@dataclass(frozen=True)
class WallPoints:
    """The measured wall points in pipe coordinates.

    Attributes:
        axial_mm: (N,) along the centreline (the defects' axial convention).
        angle_deg: (N,) omnipipe angle (report.json ``angle_deg``'s convention), [0, 360).
        deviation_mm: (N,) radial deviation from the fitted wall (+ out of the pipe).
        radius_mm: the wall's reference radius (arc length = angle x radius).
    """

    axial_mm: np.ndarray
    angle_deg: np.ndarray
    deviation_mm: np.ndarray
    radius_mm: float


def deviation_grid(
    wall: WallPoints,
    axial_range: tuple[float, float],
    angle_range: tuple[float, float],
    cell_mm: float,
    max_gap_mm: float = 25.0,
) -> np.ndarray:
    """(rows along the pipe, columns around it) mean deviation (mm), NaN where unmeasured.

    ``angle_range`` may run past 360 (or below 0): angles wrap. Rows between measured
    rows are filled linearly along the pipe across gaps up to ``max_gap_mm``.
    """
    z0, z1 = axial_range
    a0, a1 = angle_range
    cell_deg = math.degrees(cell_mm / wall.radius_mm)
    rows = max(1, int(math.ceil((z1 - z0) / cell_mm)))
    cols = max(1, int(math.ceil((a1 - a0) / cell_deg)))
    total, count = _binned(wall, (z0, a0), (cell_mm, cell_deg), (rows, cols))
    with np.errstate(invalid="ignore", divide="ignore"):
        grid = (total / count).reshape(rows, cols)
    centres = z0 + (np.arange(rows) + 0.5) * cell_mm
    for j in range(cols):
        col = grid[:, j]
        ok = np.isfinite(col)
        if ok.sum() < 2:
            continue
        zs = centres[ok]
        filled = np.interp(centres, zs, col[ok])
        # Only between measured rows, and only across gaps up to max_gap_mm.
        nxt = np.searchsorted(zs, centres)
        inside = (nxt > 0) & (nxt < len(zs))
        gap = np.full(rows, np.inf)
        gap[inside] = zs[nxt[inside]] - zs[nxt[inside] - 1]
        fill = ~ok & inside & (gap <= max_gap_mm)
        col[fill] = filled[fill]
    _fill_rows(grid, max(1, int(round(max_gap_mm / 5.0 / cell_mm))))
    return grid


_POINTS_AT_ONCE = 1 << 16
"""Points :func:`_binned` takes at a time (its temporaries a chunk's, not the run's)."""


def _binned(
    wall: WallPoints, origin: tuple[float, float], cell: tuple[float, float], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """(rows x cols,) float64 sum and int64 count of the finite deviations (mm) of the wall
    points in each cell (row-major in ``shape``; ``origin`` = (axial mm, angle deg) of cell
    (0, 0)'s corner, ``cell`` its (mm, deg) sides). A chunk of :data:`_POINTS_AT_ONCE`
    points at a time, the sums in the points' order (as one ``np.bincount`` over them
    all: the same bits), nothing of the points' length held."""
    (z0, a0), (cell_mm, cell_deg), (rows, cols) = origin, cell, shape
    total = np.zeros(rows * cols)
    count = np.zeros(rows * cols, np.int64)
    for i in range(0, len(wall.axial_mm), _POINTS_AT_ONCE):
        part = slice(i, i + _POINTS_AT_ONCE)
        dev = np.asarray(wall.deviation_mm[part])
        ang = (np.asarray(wall.angle_deg[part]) - a0) % 360.0
        r = np.floor((np.asarray(wall.axial_mm[part]) - z0) / cell_mm).astype(np.int64)
        c = np.floor(ang / cell_deg).astype(np.int64)
        keep = (r >= 0) & (r < rows) & (c >= 0) & (c < cols) & np.isfinite(dev)
        flat = r[keep] * cols + c[keep]
        np.add.at(total, flat, dev[keep].astype(np.float64))
        count += np.bincount(flat, None, rows * cols)
        drop_pages()  # this chunk's points read (omnipipe.spill): a chunk's pages resident
    return total, count


def _fill_rows(grid: np.ndarray, max_cells: int) -> None:
    """Fill NaN runs of at most ``max_cells`` inside each row linearly (in place): the
    gaps between a ring's samples when the cells are finer than their spacing."""
    cols = np.arange(grid.shape[1])
    for row in grid:
        ok = np.isfinite(row)
        if ok.sum() < 2 or ok.all():
            continue
        xs = cols[ok]
        nxt = np.searchsorted(xs, cols)
        inside = (nxt > 0) & (nxt < len(xs))
        gap = np.full(len(cols), np.inf)
        gap[inside] = xs[nxt[inside]] - xs[nxt[inside] - 1]
        fill = ~ok & inside & (gap <= max_cells + 1)
        row[fill] = np.interp(cols[fill], xs, row[ok])


def distance_axis(ax: Axes, offset_m: float, origin: str) -> None:
    """Label the vertical axis (axial mm from the first frame) as the inspector's
    distance: metres from ``origin`` (``offset_m`` + axial / 1000)."""
    import textwrap

    from matplotlib.ticker import FuncFormatter, MaxNLocator

    # Ticks at round distances (not at round axial mm shifted by the origin's offset).
    lo, hi = sorted(ax.get_ylim())
    metres = MaxNLocator(nbins=8, steps=[1, 2, 2.5, 5, 10]).tick_values(
        offset_m + lo / 1000.0, offset_m + hi / 1000.0
    )
    ax.set_yticks([(t - offset_m) * 1000.0 for t in metres if lo <= (t - offset_m) * 1000.0 <= hi])
    # The fewest decimals (at least 2) that write every tick exactly (0.025 needs 3).
    digits = next((d for d in range(2, 6) if np.allclose(np.round(metres, d), metres, atol=1e-9)), 5)
    # (+ 0.0: no "-0.00" at a row a hair before the origin)
    ax.yaxis.set_major_formatter(
        FuncFormatter(lambda z, _pos: f"{round(offset_m + z / 1000.0, digits) + 0.0:.{digits}f}")
    )
    # Wrapped to the axes' height: a long label on a short strip of wall would otherwise
    # stretch the saved figure (bbox tight) with blank space above and below it.
    fig = ax.get_figure()
    height_in = ax.get_position().height * (fig.get_figheight() if fig is not None else 4.0)
    size = float(ax.yaxis.label.get_fontsize())
    chars = max(14, int(height_in * 72.0 / (0.6 * size)))
    ax.set_ylabel("\n".join(textwrap.wrap(f"distance (m) from the {origin}", chars)))


def clock_ticks(ax: Axes, a0: float, a1: float, reference_deg: float, step_h: float = 1.0) -> None:
    """Clock labels (``h:mm``) on the horizontal axis of angles ``a0``..``a1`` (deg)."""
    step = 30.0 * step_h
    first = math.ceil((a0 - reference_deg) / step)
    ticks, labels = [], []
    k = first
    while reference_deg + k * step <= a1 + 1e-9:
        angle = reference_deg + k * step
        clock = (k * step) % 360.0
        h, m = divmod(round(clock * 2) % 720, 60)
        ticks.append(angle)
        labels.append(f"{h or 12}:{m:02d}")
        k += 1
    ax.set_xticks(ticks, labels)


def draw_relief(
    ax: Axes,
    grid: np.ndarray,
    extent: tuple[float, float, float, float],
    vmax: float,
) -> object:
    """The deviation grid on ``ax`` (angles ``extent[0:2]``, axial ``extent[2:4]``):
    blue into the pipe (bulge), red out of it (dent), grey where unmeasured; returns the
    image for a colour bar."""
    import matplotlib as mpl

    cmap = mpl.colormaps["RdBu_r"].with_extremes(bad="#bbbbbb")
    a0, a1, z0, z1 = extent
    # A band of rows at a time: the figure's resampling a band's, the same pixels.
    return imshow_in_bands(
        ax, np.ma.masked_invalid(grid), (a0, a1, z1, z0), cmap=cmap, vmin=-vmax, vmax=vmax,
        interpolation="nearest",
    )


def outline(ax: Axes, d: Defect, radius_mm: float, colour: str = "black") -> None:
    """The defect's half-height extent as a rectangle (dashed where truncated)."""
    import matplotlib.patches

    half_w = math.degrees(0.5 * d.width_mm / radius_mm)
    ax.add_patch(
        matplotlib.patches.Rectangle(
            (d.angle_deg - half_w, d.axial_start_mm),
            2 * half_w,
            d.length_mm,
            fill=False,
            ec=colour,
            lw=1.4,
            ls="--" if d.truncated else "-",
        )
    )


def defect_window(d: Defect, radius_mm: float) -> tuple[float, float, float, float]:
    """(angle_min, angle_max, axial_min, axial_max) around a defect: its extent plus half
    of it and at least 20 mm each side."""
    margin_z = max(0.5 * d.length_mm, 20.0)
    width = max(d.width_mm, 1.0)
    half_deg = math.degrees((0.5 * width + max(0.5 * width, 20.0)) / radius_mm)
    return (
        d.angle_deg - half_deg,
        d.angle_deg + half_deg,
        d.axial_start_mm - margin_z,
        d.axial_end_mm + margin_z,
    )


def relief_vmax(heights: list[float], noise_mm: float | None) -> float:
    """Colour scale limit (mm): the largest defect height, at least 3 noise sigmas and 0.5."""
    top = max([abs(h) for h in heights] + [0.5])
    return max(top, 3.0 * (noise_mm or 0.0))

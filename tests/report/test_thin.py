"""The 3-D view's thinning (omnipipe.report.thin) on a synthetic unrolled pipe mesh."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.report.thin import thin_mesh


def pipe_mesh(rows: int, cols: int = 120, radius: float = 100.0, pitch: float = 2.0):
    """A textured pipe wall as the model stage meshes it: ``rows`` rings of ``cols``
    vertices plus a seam copy of each ring's first vertex at u = 1 (mm, (V, 2) UVs,
    faces of two triangles per quad), and its texture's shape (square mm pixels)."""
    theta = np.linspace(0.0, 2 * np.pi, cols + 1)
    t, z = np.meshgrid(theta, np.arange(rows) * pitch)
    verts = np.column_stack([radius * np.cos(t.ravel()), radius * np.sin(t.ravel()), z.ravel()])
    circ, length = 2 * np.pi * radius, (rows - 1) * pitch
    uvs = np.column_stack([t.ravel() / (2 * np.pi), z.ravel() / length])
    idx = np.arange(rows * (cols + 1)).reshape(rows, cols + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return verts, faces, uvs, (int(length), int(circ))


def test_a_small_mesh_is_sent_as_it_is() -> None:
    verts, faces, uvs, shape = pipe_mesh(10)
    v, f, uv = thin_mesh(verts, faces, uvs, len(faces), shape)
    assert v is verts and uv is uvs and np.array_equal(f, faces)


def test_thinned_mesh_is_bounded_whatever_the_length_and_covers_the_wall() -> None:
    """Runs 5x apart in length give views within max_faces (the longer one's cells
    larger); every view vertex is a mesh vertex with its own UV; no face crosses the
    texture seam; the view still covers the wall: every mesh vertex lies within a few
    cells of a view vertex (no hole left where faces were taken out)."""
    max_faces = 3000
    sizes = []
    for rows in (200, 1000):
        verts, faces, uvs, shape = pipe_mesh(rows)
        v, f, uv = thin_mesh(verts, faces, uvs, max_faces, shape)
        assert 0.5 * max_faces < len(f) <= max_faces
        assert len(v) == len(np.unique(f)) <= max_faces
        mesh_rows = {tuple(r) for r in np.hstack([verts, uvs])}
        assert all(tuple(r) in mesh_rows for r in np.hstack([v, uv]))
        assert np.max(np.ptp(uv[f][:, :, 0], axis=1)) < 0.5  # the seam stays a seam
        # Cell side (mm) of this view: the wall's area over its vertices.
        side = np.sqrt(2 * np.pi * 100.0 * (rows - 1) * 2.0 / len(v))
        probe = verts[:: max(1, len(verts) // 4000)]
        gap = np.min(np.linalg.norm(probe[:, None] - v[None], axis=2), axis=1)
        assert gap.max() < 2.5 * side
        sizes.append(len(f))
    assert sizes[1] <= max_faces


def test_uvs_without_spread_fall_back_to_every_kth_face() -> None:
    verts, faces, uvs, shape = pipe_mesh(100)
    v, f, uv = thin_mesh(verts, faces, np.zeros_like(uvs), 500, shape)
    assert len(f) <= 500 and len(v) == len(uv) == len(np.unique(f))


def test_an_image_drawn_in_bands_is_the_image_drawn_whole() -> None:
    """imshow_in_bands (the unrolled wall's figure, a band of rows at a time so that
    matplotlib's float64 resampling is a band's) gives the same PNG, byte for byte, as
    one imshow of the whole image: bands that do and do not divide the rows, an image
    larger and one smaller than the axes' pixels; with and without anything autoscaled
    after it (without, the view was the last band's: the report's unrolled wall with no
    defect, feature or unreliable stretch drawn on it)."""
    import base64
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omnipipe.report.bands import imshow_in_bands

    rng = np.random.default_rng(5)

    def png(image: np.ndarray, rows: int | None, plot_after: bool) -> bytes:
        fig, ax = plt.subplots(figsize=(3, 4))
        extent = (40.0, 400.0, 310.0, -20.0)
        if rows is None:
            ax.imshow(image, extent=extent, aspect="auto", interpolation="bilinear")
        else:
            imshow_in_bands(ax, image, extent, rows)
        if plot_after:  # autoscaling after the image, as the report's markers do
            ax.plot([100.0], [50.0], marker="+")
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
        plt.close(fig)
        return base64.b64encode(buf.getvalue())

    for shape in ((700, 150, 3), (90, 500, 3)):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        for plot_after in (True, False):
            whole = png(image, None, plot_after)
            for rows in (64, 100, 1000):
                assert png(image, rows, plot_after) == whole, (shape, rows, plot_after)


def test_thinning_a_chunk_of_faces_at_a_time_keeps_the_same_view(monkeypatch) -> None:
    """The faces renumbered a chunk at a time (their temporaries a chunk's, not the
    mesh's): the same view as all at once, the repeats across chunks dropped too."""
    from omnipipe.report import thin

    verts, faces, uvs, shape = pipe_mesh(400)
    monkeypatch.setattr(thin, "FACE_CHUNK", len(faces))
    whole = thin_mesh(verts, faces, uvs, 2000, shape)
    monkeypatch.setattr(thin, "FACE_CHUNK", 997)
    chunked = thin_mesh(verts, faces.astype(np.int32), uvs, 2000, shape)
    for a, b in zip(whole, chunked, strict=True):
        assert np.array_equal(a, b)
    assert len(np.unique(np.sort(chunked[1], axis=1), axis=0)) == len(chunked[1])  # no repeats


def test_cells_a_chunk_of_vertices_at_a_time_keep_the_same_view(monkeypatch) -> None:
    """The vertices' cells found a chunk at a time (their int64 temporaries a chunk's):
    the same cells, the same first vertex of each, the same view as all at once."""
    from omnipipe.report import thin

    verts, faces, uvs, shape = pipe_mesh(400)
    monkeypatch.setattr(thin, "VERTEX_CHUNK", len(uvs))
    whole = thin_mesh(verts, faces, uvs, 2000, shape)
    n_whole = thin._cells(uvs, 3.0, shape)
    monkeypatch.setattr(thin, "VERTEX_CHUNK", 997)
    chunked = thin_mesh(verts, faces, uvs, 2000, shape)
    assert thin._cells(uvs, 3.0, shape) == n_whole > 1000
    for a, b in zip(whole, chunked, strict=True):
        assert np.array_equal(a, b)


def test_the_relief_map_drawn_in_bands_is_the_map_drawn_whole() -> None:
    """relief.draw_relief (a colour-mapped, masked deviation grid, nearest cells) drawn a
    band of rows at a time gives the same PNG, byte for byte, as one imshow, with a
    colour bar from the returned image; and matplotlib's resampling holds a band's
    pixels, not the figure's (12 inches tall: 52 MB traced drawn whole)."""
    import io
    import tracemalloc

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib as mpl
    import matplotlib.pyplot as plt

    from omnipipe.report import relief

    rng = np.random.default_rng(6)
    grid = rng.normal(0.0, 0.4, (400, 126))
    grid[rng.random(grid.shape) < 0.1] = np.nan
    extent = (10.0, 370.0, 0.0, 2000.0)

    def png(banded: bool) -> tuple[bytes, float]:
        fig, ax = plt.subplots(figsize=(9, 12))
        if banded:
            im = relief.draw_relief(ax, grid, extent, 1.0)
        else:
            cmap = mpl.colormaps["RdBu_r"].with_extremes(bad="#bbbbbb")
            im = ax.imshow(np.ma.masked_invalid(grid), extent=(10.0, 370.0, 2000.0, 0.0), aspect="auto",
                           cmap=cmap, vmin=-1.0, vmax=1.0, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8)
        ax.plot([100.0], [500.0], marker="+")
        buf = io.BytesIO()
        tracemalloc.start()
        fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        plt.close(fig)
        return buf.getvalue(), peak

    whole, whole_mb = png(False)
    banded, banded_mb = png(True)
    assert banded == whole
    assert banded_mb < 0.4 * whole_mb


@pytest.mark.slow  # a 2.4 M-vertex mesh thinned twice
@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="reads /proc/self")
def test_thinning_a_mesh_on_disk_keeps_a_chunk_of_its_pages_resident() -> None:
    """A long run's mesh waits in the run's scratch (omnipipe.spill): thinning it reads
    its UVs, faces and kept vertices a chunk at a time, the pages read dropped as it
    goes (2.4 M vertices, 58 MB of UVs and vertices, 58 MB of int32 faces: the process
    rose 190 MB when they stayed resident); the view is the one made from arrays in
    memory."""
    import threading
    import time

    from omnipipe.memory import release_freed_memory
    from omnipipe.spill import on_disk

    verts, faces, uvs, shape = pipe_mesh(6000, 400)
    faces = faces.astype(np.int32)
    expected = thin_mesh(verts, faces, uvs, 250_000, shape)
    disk = on_disk(verts), on_disk(faces), on_disk(uvs)
    del verts, faces, uvs
    release_freed_memory()

    def rss() -> float:
        with open("/proc/self/status", encoding="ascii") as fh:
            return next(int(line.split()[1]) / 1024.0 for line in fh if line.startswith("VmRSS:"))

    peak, done = [rss()], threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], rss())
            time.sleep(0.002)

    low = rss()
    thread = threading.Thread(target=sample)
    thread.start()
    try:
        got = thin_mesh(*disk, 250_000, shape)
    finally:
        done.set()
        thread.join()
    for a, b in zip(got, expected, strict=True):
        assert np.array_equal(a, b)
    assert peak[0] - low < 110

"""Model stage (paper Sec. VI): integrated wall points, mesh, texture, model files.

Integration, the unrolled Delaunay mesh and its winding: :mod:`.mesh`. Colour: the
LED-lit image a few pixels off the ring along the radial direction (at the ring itself
the laser dominates the red channel).

Texture (:mod:`.texture`): the unrolled wall image, each cell from the keyframe
that sees it best; it is also the texture atlas of the textured model (GLB).

Then the edge flips of [25] towards photo-consistency (:mod:`.flips`).

Images: the texture is made a section of :data:`~.texture_grid.SECTION_ROWS` grid rows at a
time: the section's choice of keyframe per cell (which needs no image), then each
chosen keyframe's image decoded once for the section's samples (and its ring colours,
the first time). A keyframe whose cells lie in two sections is decoded twice; the
keyframes that texture no cell are decoded once at the end for their ring colours.
With ``ModelInputs.dataset`` the decoding runs frame-parallel on the executor
(:mod:`omnipipe.executor`), else serially through ``read_frame``. The result does not
depend on which.

Files in each format's unit and axes: :mod:`.export`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace
from itertools import chain
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.config import bounded
from omnipipe.errors import ConfigError, ShapeError
from omnipipe.executor import FrameSource, InlineExecutor, chunks, ordered_map
from omnipipe.handoff import PlanarFrame, plane_split
from omnipipe.memory import release_freed_memory
from omnipipe.model.mesh import (
    atlas_margin,
    integrate,
    longest_edge,
    mesh_unrolled,
    orient_towards_axis,
    textured_mesh,
    unrolled_coordinates,
)
from omnipipe.model.outliers import OutlierConfig
from omnipipe.model.texture import paint, texture_samples
from omnipipe.model.texture_grid import SECTION_ROWS, MeshGrid, UnrolledImage
from omnipipe.model.texture_light import LightStore, flat_field
from omnipipe.model.texture_sources import LIGHT_DTYPE, choose_sources
from omnipipe.progress import phase
from omnipipe.rig import Rig
from omnipipe.spill import drop_pages, on_disk, zeros_on_disk

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.model.flips import FlipStats


@dataclass(frozen=True)
class ModelConfig:
    """Model settings.

    Attributes:
        mesher: "unrolled-delaunay" (the only one so far).
        colour_offset_px: point colours are sampled this far outside the laser ring.
        max_edge_factor: triangles with an edge longer than this x the median are dropped.
        texture: build the unrolled image, texture and GLB.
        texture_mm_per_px: unrolled image cell size (mm).
        laser_band_mm: texture is not taken within this distance of the laser plane.
        flips: edge-flip optimisation of [25] (:mod:`.flips`); off by default: on the
            simulated pipes it did not reduce the mesh's error against the true wall
            (docs/pipeline.md).
        flip_passes: its rounds.
        outliers: the stray-point rule applied to the stations' rings before
            integration (:mod:`.outliers`; ``model.outliers.*`` in YAML).
    """

    mesher: str = "unrolled-delaunay"
    colour_offset_px: float = bounded(4.0, ge=0)
    max_edge_factor: float = bounded(2.0, gt=0)
    texture: bool = True
    texture_mm_per_px: float = bounded(0.5, gt=0)
    laser_band_mm: float = bounded(3.0, ge=0)
    flips: bool = False
    flip_passes: int = bounded(3, ge=0)
    outliers: OutlierConfig = field(default_factory=OutlierConfig)

    def __post_init__(self) -> None:
        if self.mesher != "unrolled-delaunay":
            raise ConfigError(
                "model.mesher", f"unknown mesher {self.mesher!r} (known: unrolled-delaunay)"
            )


@dataclass
class ModelInputs:
    """Keyframes' rings and poses.

    Attributes:
        camera_rig: calibration.
        world_from_rig: (K, 4, 4) poses of the keyframes.
        ring_points_in_rig: K arrays (M_k, 3), mm (not read when ``points_in_world`` is
            given; may then be empty).
        ring_pixels: K arrays (M_k, 2), the rings' image positions (col, row).
        read_frame: k -> image of keyframe k.
        unrolled_mm: (N, 2) arc length around the axis in [0, circumference) and axial
            position of the integrated points (in :func:`integrate` order); None: a
            straight axis through the rig origins.
        circumference_mm: of the unrolled view (2 pi x the fitted radius).
        dataset: the opened dataset of the keyframes; with ``frame_index`` the images
            are decoded in the executor's workers (:func:`run`), not by ``read_frame``.
        handoff: the folder of a :class:`~omnipipe.handoff.FrameHandoff` where the
            run's decoding pass left frames: those are read from there, not decoded.
        frame_index: (K,) int, the dataset index of each keyframe.
        points_in_world: (N, 3) the rings already integrated, mm (:func:`integrate` of
            ``world_from_rig`` and the rings, in its order), with ``point_frame`` (N,)
            each point's keyframe: a caller that has them (the pipeline's analysis)
            passes them instead of the rings, which then need not be held through the
            stage; None: integrated here.
        point_frame: see ``points_in_world``.
        not_wall: (N,) True for the points in a joint's gap or a lateral's opening (the
            analysis' ``point_not_wall``, in :func:`integrate` order): no triangle
            touches them, so the mesh shows the gap and the hole; None: all wall.
    """

    camera_rig: Rig
    world_from_rig: np.ndarray
    ring_points_in_rig: list[np.ndarray]
    ring_pixels: list[np.ndarray]
    read_frame: Callable[[int], np.ndarray]
    unrolled_mm: np.ndarray | None = None
    circumference_mm: float | None = None
    dataset: Dataset | None = None
    handoff: str | None = None
    frame_index: np.ndarray | None = None
    points_in_world: np.ndarray | None = None
    point_frame: np.ndarray | None = None
    not_wall: np.ndarray | None = None


@dataclass
class ModelResult:
    """The model.

    Attributes:
        points_in_world: (N, 3) integrated ring points, mm.
        colours: (N, 3) uint8 colour of each point.
        point_frame: (N,) keyframe index of each point.
        mesh_vertices, mesh_faces: the wall mesh on the points ((N, 3), (F, 3)).
        textured_vertices, textured_faces, textured_uvs: the same mesh with the vertices
            of triangles across angle 0 duplicated (their UVs differ); UVs v-up in [0, 1].
        texture: (H, W', 3) uint8 atlas: the unrolled image plus a wrapped margin.
        unrolled: the unrolled wall image (:class:`~omnipipe.model.texture_grid.UnrolledImage`).
        flip_stats: what the edge flips did (:class:`~omnipipe.model.flips.FlipStats`).
    """

    points_in_world: np.ndarray
    colours: np.ndarray
    point_frame: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    textured_vertices: np.ndarray | None = None
    textured_faces: np.ndarray | None = None
    textured_uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    unrolled: UnrolledImage | None = None
    flip_stats: FlipStats | None = None


def colour_pixels(ring_pixels: np.ndarray, camera: CameraModel, offset_px: float) -> np.ndarray:
    """(M, 2) int (col, row) where the colours of a ring's (M, 2) pixels are sampled:
    ``offset_px`` outside the ring along the radial direction, rounded, in the image."""
    centre = np.array([camera.cx, camera.cy])
    radial = ring_pixels - centre
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    sample = np.round(ring_pixels + offset_px * radial).astype(int)
    sample[:, 0] = sample[:, 0].clip(0, camera.width - 1)
    sample[:, 1] = sample[:, 1].clip(0, camera.height - 1)
    return sample


def colours_at(image: np.ndarray, sample: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 colours of ``image`` ((H, W, 3) or (H, W), uint8 or uint16) at (M, 2)
    int pixels (col, row)."""
    c = image[sample[:, 1], sample[:, 0]]
    if c.ndim == 1:
        c = np.repeat(c[:, None], 3, axis=1)
    if c.dtype == np.uint16:
        c = (c // 257).astype(np.uint8)
    return c.astype(np.uint8)


@dataclass(frozen=True)
class _FrameWork:
    """What is sampled in one keyframe's image.

    Attributes:
        colour_px: (M, 2) int pixels of its ring colours (:func:`colour_pixels`).
        texture_px: (n, 2) float32 pixels of the texture cells it was chosen for, in
            pieces to concatenate (views of the choice's arrays: no copy is held).
    """

    colour_px: np.ndarray
    texture_px: tuple[np.ndarray, ...]

    def __call__(self, image: np.ndarray | PlanarFrame, laser_channel: str) -> tuple[np.ndarray, np.ndarray]:
        """((M, 3), (n, 3)) uint8: the ring colours and the texture samples in ``image``.

        An 8-bit colour frame of a red laser is sampled in its planar form
        (:meth:`PlanarFrame.sample`: red and blue from their half-resolution planes), as
        the decoding pass hands it on (:func:`~omnipipe.handoff.plane_split`), whether
        it came from there or was decoded: the same colours with or without a hand-off.
        """
        pixels = np.concatenate(self.texture_px) if self.texture_px else np.zeros((0, 2), np.float32)
        if not isinstance(image, PlanarFrame) and plane_split(image, laser_channel):
            image = PlanarFrame.of(image)
        if isinstance(image, PlanarFrame):
            return image.sample(self.colour_px), image.sample(pixels)
        colours = colours_at(image, self.colour_px) if len(self.colour_px) else np.zeros((0, 3), np.uint8)
        samples = texture_samples(image, pixels) if len(pixels) else np.zeros((0, 3), np.uint8)
        return colours, samples


_NO_PIXELS = np.zeros((0, 2), int)
"""No ring colours to sample (a keyframe's ring sampled in an earlier section)."""


class _Ticks:
    """``progress(i)`` once for every i = 1 .. total, in order, as the work gets there."""

    def __init__(self, progress: Callable[[int], None] | None, total: int) -> None:
        self._progress, self._total, self._done = progress, total, 0

    def to(self, done: int) -> None:
        """Report every tick up to ``done`` (at most the total) not reported yet."""
        for i in range(self._done + 1, min(done, self._total) + 1):
            if self._progress:
                self._progress(i)
            self._done = i


class _FramesTask:
    """Picklable task: decode each frame of a chunk once and sample what its work asks."""

    def __call__(
        self, chunk: tuple[FrameSource, tuple[_FrameWork, ...]]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        source, work = chunk
        channel = source.rig.laser.channel
        return [w(source.read(i, planar=True), channel) for i, w in enumerate(work)]


def _sample_frames(
    inputs: ModelInputs,
    work: list[_FrameWork | None],
    executor: Executor | None,
    progress: Callable[[int], None] | None,
) -> Iterator[tuple[int, tuple[np.ndarray, np.ndarray]]]:
    """(k, result) of each keyframe k with work, its work done on its image, in order of k
    (consumed as they come: the results of the run are not all held at once). Each
    keyframe's entry of ``work`` is set to None once its result is consumed, so that
    its pixels are freed as the run goes, not at its end.

    With ``inputs.dataset`` and ``inputs.frame_index``: consecutive chunks of the
    keyframes that have work, decoded and sampled by ``executor``'s workers (each chunk
    carries only its own keyframes' pixels); otherwise serially via ``inputs.read_frame``.
    ``progress(k + 1)`` after keyframe k (after its result is consumed).
    """
    # Keyframe indices only: each work item is referenced by ``work`` alone (and by its
    # chunk while in flight), so it is dropped once its result is consumed.
    todo = [k for k, w in enumerate(work) if w is not None]
    results: Iterator[tuple[np.ndarray, np.ndarray]]
    if inputs.dataset is not None and inputs.frame_index is not None:
        frame_index = np.asarray(inputs.frame_index)
        if frame_index.shape != (len(work),):
            raise ShapeError(
                f"frame_index: expected shape ({len(work)},) (one per keyframe), got {frame_index.shape}"
            )
        ex = executor if executor is not None else InlineExecutor()
        dataset = inputs.dataset
        items = (
            (
                FrameSource.take(
                    dataset, [int(frame_index[k]) for k in todo[part.start : part.stop]],
                    handoff=inputs.handoff, planar=True,
                ),
                tuple(work[k] for k in todo[part.start : part.stop]),
            )
            for part in chunks(len(todo), ex)
        )
        results = chain.from_iterable(ordered_map(ex, _FramesTask(), items))
    else:
        channel = inputs.camera_rig.laser.channel
        results = (work[k](inputs.read_frame(k), channel) for k in todo)  # type: ignore[misc]
    for k in range(len(work)):
        if work[k] is not None:
            yield k, next(results)
            work[k] = None  # its pixels are done with
        if progress:
            progress(k + 1)


def _integrated(inputs: ModelInputs) -> tuple[np.ndarray, np.ndarray]:
    """``inputs``' own integrated points and their keyframes, checked.

    Raises:
        ShapeError: not (N, 3) points with (N,) keyframe indices below K.
    """
    points = np.asarray(inputs.points_in_world, float)
    frame = None if inputs.point_frame is None else np.asarray(inputs.point_frame)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ShapeError(f"model inputs: points_in_world must be (N, 3), got {points.shape}")
    if frame is None or frame.shape != (len(points),) or frame.dtype.kind not in "iu":
        raise ShapeError("model inputs: point_frame must be (N,) integers with points_in_world")
    if len(frame) and not _all_within(frame, len(inputs.world_from_rig)):
        raise ShapeError("model inputs: point_frame must index world_from_rig's keyframes")
    return points, frame


def _all_within(index: np.ndarray, k: int, block: int = 1 << 18) -> bool:
    """True when every value of the (N,) integers ``index`` lies in [0, k): a block at a
    time, each block's pages dropped after it (an array in the run's scratch,
    :func:`~omnipipe.spill.drop_pages`: a whole-run pass maps a block of the run)."""
    for a in range(0, len(index), block):
        part = index[a : a + block]
        ok = part.min() >= 0 and part.max() < k
        drop_pages()
        if not ok:
            return False
    return True


class _RingColours:
    """Each keyframe's ring colours, sampled the first time its image is read."""

    def __init__(
        self, inputs: ModelInputs, camera: CameraModel, offset_px: float, executor: Executor | None
    ) -> None:
        self.inputs, self.camera, self.offset_px, self.executor = inputs, camera, offset_px, executor
        self.colours_of: list[np.ndarray | None] = [None] * len(inputs.ring_pixels)

    def to_sample(self, k: int) -> np.ndarray | None:
        """Keyframe k's (M, 2) ring colour pixels if its ring is not sampled yet, else None
        (made when its image is next read: not held for every keyframe at once)."""
        px = self.inputs.ring_pixels[k]
        if not len(px) or self.colours_of[k] is not None:
            return None
        return colour_pixels(px, self.camera, self.offset_px)

    def sample(self, work: list[_FrameWork | None]) -> Iterator[tuple[int, np.ndarray]]:
        """(k, texture samples) per keyframe with work; its ring colours kept once."""
        for k, (ring_colours, samples) in _sample_frames(self.inputs, work, self.executor, None):
            if len(ring_colours) and self.colours_of[k] is None:
                self.colours_of[k] = ring_colours
            yield k, samples


def _texture(
    config: ModelConfig,
    inputs: ModelInputs,
    rings: _RingColours,
    ticks: _Ticks,
    points: np.ndarray,
    faces: np.ndarray,
    unrolled_at: tuple[np.ndarray, np.ndarray, float],
    executor: Executor | None,
) -> tuple[UnrolledImage, np.ndarray]:
    """The unrolled wall image (a view of the atlas) and the texture atlas
    (:func:`~omnipipe.model.mesh.textured_mesh`'s margin not filled yet): each cell from
    the keyframe that sees it best.

    A section of the pipe at a time: its cells chosen, then sampled in the images of the
    keyframes chosen for them (the chosen pixels, 8 bytes a cell, are a section's, not the
    run's). A keyframe that textures two sections is read twice.

    Args:
        points, faces: the mesh (mm; (F, 3) vertex indices).
        unrolled_at: (N,) arc and (N,) axial position of the points (mm), circumference (mm).
    """
    arc, axial, circ = unrolled_at
    # Holes stay holes: a cell counts as wall when it is no farther from a point than
    # the inside of the largest kept triangle (0.6 x its longest edge).
    longest = longest_edge(points, faces)
    gap = 0.6 * longest
    # The grid is evaluated and scored a strip of rows at a time (never held whole), on
    # the mesh's own triangles: the ones it drops (a lateral's opening, a joint's gap, an
    # edge longer than its longest, e.g. across the wall under water) stay holes in the
    # texture too.
    wall = MeshGrid(faces, arc, axial, points, circ, config.texture_mm_per_px, max(gap, 2.0))
    h, w = wall.shape
    wall_z0 = wall.axial_min_mm
    seen = zeros_on_disk((h, w), bool)  # the cells some keyframe textures
    # Painted straight into the texture atlas (the unrolled image plus its wrapped margin,
    # textured_mesh): the image is held once, in the run's scratch (omnipipe.spill: a
    # section's rows resident at a time). Each cell's view, for the flat field, waits
    # on disk a section at a time (4 bytes a cell, the largest of the grid's arrays).
    atlas = zeros_on_disk((h, w + atlas_margin(w), 3), np.uint8)
    light = LightStore(h, w, LIGHT_DTYPE)
    try:
        for top in range(0, h, SECTION_ROWS):
            end = min(top + SECTION_ROWS, h)
            seen[top:end] = _texture_section(
                config, inputs, rings, ticks, wall, (top, end), executor, atlas, light
            )
        del wall
        release_freed_memory()  # the wall grid's blocks and the strips' results
        unrolled = UnrolledImage(atlas[:, :w], seen, config.texture_mm_per_px, wall_z0, circ)
        # The LEDs' falloff and the vignetting out, in place.
        return flat_field(unrolled, light, in_place=True), atlas
    finally:
        light.close()


def _texture_section(
    config: ModelConfig,
    inputs: ModelInputs,
    rings: _RingColours,
    ticks: _Ticks,
    wall: MeshGrid,
    rows: tuple[int, int],
    executor: Executor | None,
    atlas: np.ndarray,
    light: LightStore,
) -> np.ndarray:
    """Rows ``[top, end)`` of the unrolled wall: their cells chosen, then sampled in the
    images of the keyframes chosen for them and painted into ``atlas``; their light
    appended to ``light``. Returns (end - top, W) bool: the cells some keyframe textures."""
    top, end = rows
    h, w = wall.shape
    n_k = len(inputs.ring_pixels)
    # Progress: a section's rows count half for the choice of its cells (strip by
    # strip), half for sampling them (keyframe by keyframe).
    choice = choose_sources(
        inputs.camera_rig, inputs.world_from_rig, wall, config.texture_mm_per_px,
        config.laser_band_mm, executor=executor, rows=(top, end),
        rows_done=lambda r: ticks.to(n_k * (2 * top + r) // (2 * h)),
    )
    seen = choice.source >= 0
    light.append(choice.light)
    work: list[_FrameWork | None] = [None] * n_k
    for k in range(n_k):
        if choice.count(k):
            ring = rings.to_sample(k)
            work[k] = _FrameWork(_NO_PIXELS if ring is None else ring, choice.pieces[k])
    choice = replace(choice, pieces=(), light=None)  # each keyframe's dropped once sampled
    todo = max(1, sum(item is not None for item in work))
    image = np.zeros(((end - top) * w, 3), np.uint8)  # the section's cells, row-major
    for i, (k, samples) in enumerate(rings.sample(work), start=1):
        paint(image, choice, k, samples)
        ticks.to(n_k * (2 * top * todo + (end - top) * (todo + i)) // (2 * h * todo))
    atlas[top:end, :w] = image.reshape(end - top, w, 3)
    del work, choice, image
    release_freed_memory()  # the section's strips, pixels and samples
    ticks.to(n_k * end // h)
    return seen


def run(
    config: ModelConfig,
    inputs: ModelInputs,
    progress: Callable[[int], None] | None = None,
    executor: Executor | None = None,
) -> ModelResult:
    """Integrate the rings, mesh the wall, choose each texture cell's keyframe, then read
    each keyframe's image once for its ring colours and texture samples.

    Args:
        config: model settings.
        inputs: keyframes; with ``inputs.dataset`` and ``inputs.frame_index`` the images
            are decoded on ``executor`` (default: inline), else by ``inputs.read_frame``.
        progress: called with k + 1 after keyframe k's image is done.
        executor: frame-parallel work (:mod:`omnipipe.executor`); the result does not
            depend on it.
    """
    # The stage's BLAS work is small products (3 columns, barycentric transforms): BLAS
    # threads gain nothing there and, on cores shared with workers, their spinning can
    # stall the stage for minutes.
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(config, inputs, progress, executor)


def _run(
    config: ModelConfig,
    inputs: ModelInputs,
    progress: Callable[[int], None] | None,
    executor: Executor | None,
) -> ModelResult:
    """:func:`run` (BLAS threads already limited)."""
    camera = camera_from_rig(inputs.camera_rig)
    if inputs.points_in_world is not None:
        points, frame = _integrated(inputs)
    else:
        points, frame = integrate(inputs.world_from_rig, inputs.ring_points_in_rig)
    if not len(points):
        empty = np.zeros((0, 3))
        return ModelResult(
            empty, np.zeros((0, 3), np.uint8), np.zeros(0, int), empty, np.zeros((0, 3), int)
        )
    if inputs.unrolled_mm is not None:
        arc, axial = inputs.unrolled_mm[:, 0], inputs.unrolled_mm[:, 1]
        circ = float(inputs.circumference_mm)
    else:
        arc, axial, circ = unrolled_coordinates(points, inputs.world_from_rig)
    faces = mesh_unrolled(
        arc, axial, points, circ, config.max_edge_factor, hole=inputs.not_wall, executor=executor
    )
    flip_stats = None
    if config.flips and len(faces):
        from omnipipe.image import gray_without_laser
        from omnipipe.model.flips import optimise_flips

        channel = inputs.camera_rig.laser.channel
        tick = phase("mesh", len(inputs.world_from_rig))  # the stations' images, read once

        def read_gray(k: int) -> np.ndarray:
            gray = gray_without_laser(inputs.read_frame(k), channel)
            tick(k + 1)
            return gray

        faces, flip_stats = optimise_flips(
            faces, points, np.column_stack([arc, axial]), circ, camera, inputs.world_from_rig,
            read_gray, passes=config.flip_passes,
        )
    faces = on_disk(orient_towards_axis(faces, arc, axial, circ, points, frame))
    release_freed_memory()  # the triangulation's chunks (qhull's many small blocks)
    n_k = len(inputs.ring_pixels)
    rings = _RingColours(inputs, camera, config.colour_offset_px, executor)
    ticks = _Ticks(progress, n_k)
    unrolled: UnrolledImage | None = None
    atlas: np.ndarray | None = None
    if config.texture and len(faces):
        unrolled, atlas = _texture(config, inputs, rings, ticks, points, faces, (arc, axial, circ), executor)
        release_freed_memory()  # the flat field's estimate (its cells' arrays) not under the seam split
    # The rings of the keyframes that textured no cell.
    rest = [None if (ring := rings.to_sample(k)) is None else _FrameWork(ring, ()) for k in range(n_k)]
    for _ in rings.sample(rest):
        pass
    ticks.to(n_k)
    colours = np.concatenate([c for c in rings.colours_of if c is not None])
    del rest
    result = ModelResult(points, colours, frame, points, faces, flip_stats=flip_stats)
    if unrolled is not None:
        verts, tfaces, uvs, atlas = textured_mesh(faces, points, arc, axial, unrolled, atlas)
        result.textured_vertices, result.textured_faces, result.textured_uvs = verts, tfaces, uvs
        # The unrolled image is the atlas's first W columns: a view of it, so the image is
        # held once, not twice.
        result.texture, result.unrolled = atlas, unrolled
        del unrolled
    return result

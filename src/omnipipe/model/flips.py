"""Mesh optimisation by edge flips (paper Sec. VI after Nakatsuji, Sugaya and Kanatani [25]).

Two triangles sharing an edge span a quadrilateral that can be split along either
diagonal. Where the wall is not flat (a bulge's flank, a dent's rim, a weld), only one
diagonal follows the true surface; the other cuts through or floats above it. The two
splits place the quad's interior at different 3-D points, and a wrong surface shows
the wall texture at the wrong place in each image: the images that see the quad
disagree. For every interior edge, both splits are sampled at a few barycentric
points, projected into the two stations that see the quad best, and compared (mean
squared grey difference after removing each view's mean); the edge is flipped when
the other diagonal is markedly more consistent. Flips are applied in passes over
edges that share no triangle, and only where the quad is convex in the unrolled
parameterisation, so the mesh stays a valid, non-crossing surface.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.geometry import apply, invert
from omnipipe.image import sample_bilinear

# Barycentric sample points inside a triangle (all weights positive).
_BARY = np.array(
    [
        [1 / 3, 1 / 3, 1 / 3],
        [0.6, 0.2, 0.2],
        [0.2, 0.6, 0.2],
        [0.2, 0.2, 0.6],
        [0.45, 0.45, 0.1],
        [0.1, 0.45, 0.45],
        [0.45, 0.1, 0.45],
    ]
)


@dataclass(frozen=True)
class FlipStats:
    """What the optimisation did: flips per pass and the mean photo-inconsistency."""

    flips: list[int]
    cost_before: float
    cost_after: float


def _interior_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E, 2) vertex pairs shared by exactly two faces and (E, 2) those faces."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    f = np.tile(np.arange(len(faces)), 3)
    key = np.sort(e, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, f = key[order], f[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    i = np.flatnonzero(same)
    # Exactly two: not also equal to the next one.
    single = np.ones(len(i), bool)
    if len(i) > 1:
        single[1:] &= i[1:] != i[:-1] + 1
        single[:-1] &= i[:-1] + 1 != i[1:]
    i = i[single]
    return key[i], np.stack([f[i], f[i + 1]], axis=1)


def _opposite(faces: np.ndarray, face: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """(E,) the vertex of each face not on its edge."""
    tri = faces[face]
    mask = (tri != edge[:, [0]]) & (tri != edge[:, [1]])
    return tri[np.arange(len(tri)), np.argmax(mask, axis=1)]


def _cross2(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a[:, 0] - o[:, 0]) * (b[:, 1] - o[:, 1]) - (a[:, 1] - o[:, 1]) * (b[:, 0] - o[:, 0])


def optimise_flips(
    faces: np.ndarray,
    points_in_world: np.ndarray,
    unrolled_mm: np.ndarray,
    circumference_mm: float,
    camera: CameraModel,
    world_from_rig: np.ndarray,
    read_gray: Callable[[int], np.ndarray],
    *,
    passes: int = 3,
    min_gain: float = 0.5,
) -> tuple[np.ndarray, FlipStats]:
    """Flip edges towards photo-consistency (see the module docstring).

    Args:
        faces: (F, 3) triangles.
        points_in_world: (N, 3) vertices, mm.
        unrolled_mm: (N, 2) arc length and axial position of the vertices.
        circumference_mm: period of the arc length.
        camera: the omni camera.
        world_from_rig: (K, 4, 4) station poses.
        read_gray: k -> (H, W) float32 grey image of station k (without the laser channel).
        passes: rounds of flips.
        min_gain: flip when the other split's cost is below (1 - min_gain) x this one's.

    Returns:
        The new faces and what was done.
    """
    faces = faces.copy()
    if len(faces) < 2 or len(world_from_rig) < 2:
        return faces, FlipStats([], 0.0, 0.0)
    images = [read_gray(k) for k in range(len(world_from_rig))]
    rig_from_world = np.array([invert(T) for T in world_from_rig])
    centres = world_from_rig[:, :3, 3]
    flips: list[int] = []
    first_cost = last_cost = 0.0
    for it in range(passes):
        edges, pair = _interior_edges(faces)
        if not len(edges):
            break
        a, b = edges[:, 0], edges[:, 1]
        c = _opposite(faces, pair[:, 0], edges)
        d = _opposite(faces, pair[:, 1], edges)
        # The two views: the stations nearest the quad's centre (near and frontal in a pipe).
        mid = points_in_world[[a, b, c, d]].mean(axis=0)
        dist = np.linalg.norm(mid[:, None, :] - centres[None, :, :], axis=2)
        views = np.argsort(dist, axis=1)[:, :2]
        cost_now = _cost(points_in_world, [(a, b, c), (a, b, d)], views, camera, rig_from_world, images)
        cost_alt = _cost(points_in_world, [(c, d, a), (c, d, b)], views, camera, rig_from_world, images)
        if it == 0:
            first_cost = float(np.nanmean(cost_now))
        # Convex quads only (in the unrolled plane, arc unwrapped around a).
        pa, pb, pc, pd = (_local(unrolled_mm, v, a, circumference_mm) for v in (a, b, c, d))
        # c and d on opposite sides of ab, a and b on opposite sides of cd: convex.
        convex = (_cross2(pa, pb, pc) * _cross2(pa, pb, pd) < 0) & (_cross2(pc, pd, pa) * _cross2(pc, pd, pb) < 0)
        # The new diagonal may not be longer than the quad's longest side (no slivers
        # reaching across rings).
        P = points_in_world
        side = np.max(np.stack([np.linalg.norm(P[x] - P[y], axis=1) for x, y in ((a, c), (c, b), (b, d), (d, a))]), axis=0)
        convex &= np.linalg.norm(P[c] - P[d], axis=1) <= side
        better = convex & np.isfinite(cost_now) & np.isfinite(cost_alt) & (cost_alt < (1 - min_gain) * cost_now)
        # Independent flips: no two chosen edges share a face (greedy by gain).
        cand = np.flatnonzero(better)
        cand = cand[np.argsort(cost_alt[cand] - cost_now[cand])]
        n_flip = _flip(faces, pair, cand, (a, b, c, d))
        flips.append(n_flip)
        final = np.where(better & np.isin(np.arange(len(cost_now)), cand), cost_alt, cost_now)
        last_cost = float(np.nanmean(final))
        if n_flip == 0:
            break
    return faces, FlipStats(flips, first_cost, last_cost)


def _flip(
    faces: np.ndarray,
    pair: np.ndarray,
    cand: np.ndarray,
    quads: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> int:
    """Flip the candidate edges ``cand`` (best first) of ``faces`` in place, no two that
    share a face; returns how many. ``pair``: (E, 2) the faces of each edge; ``quads``:
    (E,) vertices a, b (the edge) and c, d (opposite) of each edge's quad."""
    a, b, c, d = quads
    used = np.zeros(len(faces), bool)
    n_flip = 0
    for e in cand:
        f0, f1 = pair[e]
        if used[f0] or used[f1]:
            continue
        used[f0] = used[f1] = True
        # Keep each face's orientation: a -> b -> c in f0 becomes c -> d -> ... consistently.
        if _orientation(faces[f0], a[e], b[e]):
            faces[f0] = [c[e], a[e], d[e]]
            faces[f1] = [d[e], b[e], c[e]]
        else:
            faces[f0] = [c[e], b[e], d[e]]
            faces[f1] = [d[e], a[e], c[e]]
        n_flip += 1
    return n_flip


def _local(uv: np.ndarray, v: np.ndarray, ref: np.ndarray, circ: float) -> np.ndarray:
    """Unrolled positions of vertices v with the arc unwrapped around vertices ref."""
    p = uv[v].astype(float)
    p[:, 0] = (p[:, 0] - uv[ref, 0] + 0.5 * circ) % circ - 0.5 * circ
    return p


def _orientation(face: np.ndarray, a: int, b: int) -> bool:
    """True when the face runs a -> b (else b -> a)."""
    i = int(np.flatnonzero(face == a)[0])
    return int(face[(i + 1) % 3]) == b


def _cost(points, tris, views, camera, rig_from_world, images) -> np.ndarray:
    """(E,) mean squared zero-mean grey difference between the two views over two triangles."""
    samples = []
    for v0, v1, v2 in tris:
        p = (
            _BARY[None, :, 0, None] * points[v0][:, None, :]
            + _BARY[None, :, 1, None] * points[v1][:, None, :]
            + _BARY[None, :, 2, None] * points[v2][:, None, :]
        )
        samples.append(p)
    pts = np.concatenate(samples, axis=1)  # (E, S, 3)
    E, S = pts.shape[:2]
    vals = np.full((2, E, S), np.nan, np.float32)
    for j in range(2):
        for k in np.unique(views[:, j]):
            sel = np.flatnonzero(views[:, j] == k)
            q = apply(rig_from_world[k], pts[sel].reshape(-1, 3))
            px, ok = camera.project(q)
            v = sample_bilinear(images[k], np.nan_to_num(px, nan=-1.0))
            vals[j, sel] = np.where(ok, v, np.nan).reshape(len(sel), S)
    dv = vals - np.nanmean(vals, axis=2, keepdims=True)
    return np.nanmean((dv[0] - dv[1]) ** 2, axis=1)

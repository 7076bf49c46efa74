"""Edge flips ([25]) keep a valid wall mesh and lower the photo-inconsistency they optimise."""

from __future__ import annotations

import numpy as np

from omnipipe.model import ModelConfig, ModelInputs, run


def test_flips_keep_a_manifold_wall_and_lower_their_cost(rendered_stations) -> None:
    st = rendered_stations
    scenario, poses, keep, frames, rings = st.scenario, st.poses, st.keep, st.frames, st.rings
    inputs = ModelInputs(
        scenario.rig, poses[keep], [r.points_in_rig for r in rings.rings], [r.pixels for r in rings.rings],
        lambda k: frames[int(keep[k])],
    )
    plain = run(ModelConfig(texture=False), inputs)
    flipped = run(ModelConfig(texture=False, flips=True), inputs)
    stats = flipped.flip_stats
    assert sum(stats.flips) > 0
    assert stats.cost_after < stats.cost_before
    faces = flipped.mesh_faces
    assert len(faces) == len(plain.mesh_faces)
    # Manifold: every edge in at most two triangles; no degenerate triangle.
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert counts.max() <= 2
    assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2]))
    p = flipped.points_in_world[faces]
    longest_before = np.linalg.norm(plain.points_in_world[plain.mesh_faces] - np.roll(plain.points_in_world[plain.mesh_faces], 1, axis=1), axis=2).max()
    assert np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2).max() <= longest_before + 1e-6

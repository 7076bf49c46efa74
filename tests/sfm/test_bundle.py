"""Bundle adjustment and resection on a synthetic pipe: exact geometry, noisy pixels."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply, invert, make_transform
from omnipipe.sfm.bundle import (
    BundleConfig,
    BundleProblem,
    _select_tracks,
    build_problem,
    bundle_adjust,
    cross_rows,
    epipolar_rows,
    resect_rays,
)
from omnipipe.sfm.geometry import triangulate_pairs
from omnipipe.sim.scenario import paper_rig


def _scene(pipe_scene, seed: int):
    rng = np.random.default_rng(seed)
    rig = paper_rig(800, 600)
    camera = OmniCamera.from_rig(rig)
    K = 7
    # Wall points of a 202 mm pipe around the z axis.
    poses, _, pts = pipe_scene(rng, K, 0.01, 0.5, 1500, (-250.0, 150.0))
    obs_f, obs_p, obs_px = [], [], []
    for k in range(K):
        px, ok = camera.project(apply(invert(poses[k]), pts))
        for p in np.flatnonzero(ok):
            obs_f.append(k)
            obs_p.append(p)
            obs_px.append(px[p] + rng.normal(0, 0.3, 2))
    # Laser anchors: ring points (z = -82 in rig a) seen again in the next frame.
    ring_th = np.linspace(-np.pi, np.pi, 60, endpoint=False)
    aa, ab, aq, apx = [], [], [], []
    for k in range(K - 1):
        q_a = np.column_stack([101 * np.cos(ring_th), 101 * np.sin(ring_th), np.full(60, -82.0)])
        px, ok = camera.project(apply(invert(poses[k + 1]) @ poses[k], q_a))
        aa += [k] * int(ok.sum())
        ab += [k + 1] * int(ok.sum())
        aq.append(q_a[ok])
        apx.append(px[ok] + rng.normal(0, 0.3, (int(ok.sum()), 2)))
    return rng, camera, poses, pts, (np.array(obs_f), np.array(obs_p), np.array(obs_px)), (
        np.array(aa), np.array(ab), np.concatenate(aq), np.concatenate(apx))


def test_bundle_adjustment_recovers_metric_poses_from_a_scaled_noisy_start(pipe_scene) -> None:
    rng, camera, poses, pts, (f, p, px), (aa, ab, aq, apx) = _scene(pipe_scene, 3)
    start = poses.copy()
    start[1:, :3, 3] *= 1.05  # 5 % scale error, as a poor laser step would leave
    for k in range(1, len(start)):
        start[k] = start[k] @ make_transform(Rotation.from_rotvec(rng.normal(0, 0.004, 3)).as_matrix(),
                                             rng.normal(0, 0.5, 3))
    pts0 = pts + rng.normal(0, 2.0, pts.shape)
    problem = BundleProblem(start, pts0, f, p, px, aa, ab, aq, apx)
    res = bundle_adjust(camera, problem, BundleConfig(max_evaluations=100))
    err_t = np.linalg.norm(res.world_from_rig[:, :3, 3] - poses[:, :3, 3], axis=1)
    # The 5 % scale error (3.6 mm at the last frame) is gone: what stays is the noise of
    # 0.3 px anchors at 800x600 (the optimum from the true start is as far off).
    assert err_t.max() < 0.4, err_t  # mm over 72 mm
    for T_est, T_true in zip(res.world_from_rig, poses, strict=True):
        angle = np.linalg.norm(Rotation.from_matrix(T_est[:3, :3].T @ T_true[:3, :3]).as_rotvec())
        assert np.degrees(angle) < 0.05  # start: ~0.3 deg off
    assert res.rms_after_px < 0.5 < res.rms_before_px


def test_resection_from_rays_to_known_points(pipe_scene) -> None:
    rng, camera, poses, pts, *_ = _scene(pipe_scene, 5)
    truth = poses[3]
    q = apply(invert(truth), pts)
    _, ok = camera.project(q)
    rays = q[ok] / np.linalg.norm(q[ok], axis=1, keepdims=True)
    rays = rays + rng.normal(0, 0.001, rays.shape)  # ~0.06 deg
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    wrong = rng.random(len(rays)) < 0.1
    rays[wrong] = rng.normal(size=(int(wrong.sum()), 3))
    rays[wrong] /= np.linalg.norm(rays[wrong], axis=1, keepdims=True)
    est = resect_rays(rays, pts[ok], poses[2])  # start: the previous keyframe, 12 mm back
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 0.1


def test_resection_refits_without_unverified_matches(pipe_scene) -> None:
    # A frame between keyframes: few tracked points, and the next keyframe's descriptor
    # matches (not verified by RANSAC) bring many wrong ones; the refit on the consistent
    # rays keeps the position as good as the verified ones alone would give.
    rng, camera, poses, pts, *_ = _scene(pipe_scene, 11)
    truth = poses[3] @ make_transform(np.eye(3), np.array([0.3, -0.2, 4.0]))
    q = apply(invert(truth), pts)
    _, ok = camera.project(q)
    idx = rng.choice(np.flatnonzero(ok), 60, replace=False)
    rays = q[idx] / np.linalg.norm(q[idx], axis=1, keepdims=True)
    rays = rays + rng.normal(0, 0.003, rays.shape)  # ~0.17 deg, as measured on wall features
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    wrong = np.arange(60) >= 36  # 40 % wrong
    rays[wrong] = rng.normal(size=(int(wrong.sum()), 3))
    rays[wrong] /= np.linalg.norm(rays[wrong], axis=1, keepdims=True)
    clean = resect_rays(rays[~wrong], pts[idx][~wrong], poses[3])
    est = resect_rays(rays, pts[idx], poses[3])
    err_clean = np.linalg.norm(clean[:3, 3] - truth[:3, 3])
    err = np.linalg.norm(est[:3, 3] - truth[:3, 3])
    assert err < max(1.5 * err_clean, 0.1), (err, err_clean)


def _triangulate_track_reference(camera, world_from_rig, rays_in_rig, f, li, obs, config):
    """build_problem's former per-track triangulation, the reference of the batched one."""
    R = world_from_rig[:, :3, :3]
    C = world_from_rig[:, :3, 3]
    d = np.array([R[k] @ rays_in_rig[k][j] for k, j in zip(f, li, strict=True)])
    if d[0] @ d[-1] > np.cos(np.radians(config.min_parallax_deg)):
        return None
    k1, k2 = f[0], f[-1]
    pair, depth = triangulate_pairs(
        rays_in_rig[k1][li[0]][None], rays_in_rig[k2][li[-1]][None],
        invert(world_from_rig[k2]) @ world_from_rig[k1],
    )
    if not (depth[0, 0] > 0 and depth[0, 1] > 0):
        return None
    X = R[k1] @ pair[0] + C[k1]
    q = np.einsum("nji,nj->ni", R[f], X - C[f])
    px, valid = camera.project(q)
    if not valid.all() or np.max(np.linalg.norm(px - obs, axis=1)) > config.max_reprojection_px:
        return None
    return X


def test_build_problem_triangulates_tracks_as_one_at_a_time(pipe_scene) -> None:
    """The batched track triangulation keeps the same tracks with the same points as the
    track-by-track reference: parallax, behind-the-rig and reprojection rejections
    included."""
    rng = np.random.default_rng(5)
    camera = OmniCamera.from_rig(paper_rig(800, 600))
    K = 6
    poses, _, pts = pipe_scene(rng, K, 0.01, 0.5, 600, (-250.0, 150.0))
    pixels, rays, ids = [], [], []
    for k in range(K):
        q = apply(invert(poses[k]), pts)
        px, ok = camera.project(q)
        sel = rng.permutation(np.flatnonzero(ok))[: int(0.8 * ok.sum())]
        noisy = px[sel] + rng.normal(0, 0.3, (len(sel), 2))
        noisy[rng.random(len(sel)) < 0.05] += 12.0  # a few far off: rejected by reprojection
        pixels.append(noisy)
        r = q[sel] / np.linalg.norm(q[sel], axis=1, keepdims=True)
        r[rng.random(len(sel)) < 0.03] *= -1  # a few behind the rig
        rays.append(r)
        ids.append(sel)
    matches = []
    for a in range(K - 1):
        for b in (a + 1, a + 2):
            if b >= K:
                continue
            common, ia, ib = np.intersect1d(ids[a], ids[b], return_indices=True)
            keep = rng.random(len(common)) < 0.7
            matches.append((a, b, np.stack([ia[keep], ib[keep]], axis=1)))
    config = BundleConfig(min_parallax_deg=2.0)
    problem = build_problem(camera, poses, pixels, rays, matches, [], config)
    ref_pts, ref_f, ref_p, ref_px = [], [], [], []
    ref_fp = [np.full(len(p), -1) for p in pixels]
    for f, li in _select_tracks(pixels, matches, config.max_tracks):
        obs = np.array([pixels[k][j] for k, j in zip(f, li, strict=True)])
        X = _triangulate_track_reference(camera, poses, rays, f, li, obs, config)
        if X is None:
            continue
        for k, j in zip(f, li, strict=True):
            ref_fp[k][j] = len(ref_pts)
        ref_f.append(f)
        ref_p.append(np.full(len(f), len(ref_pts)))
        ref_px.append(obs)
        ref_pts.append(X)
    n_tracks = len(_select_tracks(pixels, matches, config.max_tracks))
    assert 50 < len(ref_pts) < n_tracks - 20  # some of each rejection happened
    np.testing.assert_allclose(problem.points_in_world, np.array(ref_pts), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(problem.obs_frame, np.concatenate(ref_f))
    np.testing.assert_array_equal(problem.obs_point, np.concatenate(ref_p))
    np.testing.assert_array_equal(problem.obs_pixels, np.concatenate(ref_px))
    for got, want in zip(problem.feature_point, ref_fp, strict=True):
        np.testing.assert_array_equal(got, want)


def _matched_along(camera, start_b_from_a, true_b_from_a, q_a, rng):
    """Pixels of laser points ``q_a`` (L, 3) found in b by a search along the epipolar
    curves of ``start_b_from_a`` (as Eq. 17's template match): per point the curve's
    pixel nearest its true image, plus 0.1 px along the curve."""
    true_px, _ = camera.project(apply(true_b_from_a, q_a))
    d = start_b_from_a[:3, 3] / np.linalg.norm(start_b_from_a[:3, 3])
    s = np.linspace(2.0, 30.0, 2801)
    out = np.empty((len(q_a), 2))
    for i, q in enumerate(q_a):
        curve, _ = camera.project((start_b_from_a[:3, :3] @ q)[None] + s[:, None] * d)
        j = int(np.nanargmin(np.linalg.norm(curve - true_px[i], axis=1)))
        t = curve[min(j + 1, len(s) - 1)] - curve[max(j - 1, 0)]
        out[i] = curve[j] + rng.normal(0, 0.1) * t / np.linalg.norm(t)
    return out


def _along_anchors(camera, poses, start, rng):
    """Ring points of each keyframe (z = -82 mm in its rig) found in the next along the
    epipolar curves of the ``start`` poses: (a, b, points in a, pixels in b)."""
    ring_th = np.linspace(-np.pi, np.pi, 120, endpoint=False)
    q_a = np.column_stack([101 * np.cos(ring_th), 101 * np.sin(ring_th), np.full(120, -82.0)])
    aa, ab, aq, apx = [], [], [], []
    for k in range(len(poses) - 1):
        true_ba, start_ba = invert(poses[k + 1]) @ poses[k], invert(start[k + 1]) @ start[k]
        pix = _matched_along(camera, start_ba, true_ba, q_a, rng)
        ok = np.isfinite(pix).all(axis=1)
        aa += [k] * int(ok.sum())
        ab += [k + 1] * int(ok.sum())
        aq.append(q_a[ok])
        apx.append(pix[ok])
    return np.array(aa), np.array(ab), np.concatenate(aq), np.concatenate(apx)


def test_laser_anchors_measured_along_their_curve_do_not_hold_the_search_motion(pipe_scene) -> None:
    """Laser matches searched along the epipolar curves of a motion whose steps turned
    0.3 or 1.0 deg too far (about x, across the pipe): with both pixel components as
    residuals the adjustment's optimum moves towards that motion (the across component
    is the search's assumption, not a measurement), the more the further it was off;
    with only the component along the curve (:func:`epipolar_rows`) it stays where the
    features put it, whatever the search assumed. Adjusted from the true poses, so
    that only the optimum's place is compared."""
    rng, camera, poses, pts, (f, p, px), _ = _scene(pipe_scene, 4)
    errors = {}
    for deg in (0.3, 1.0):
        start = poses.copy()
        for k in range(1, len(poses)):
            turn = make_transform(Rotation.from_rotvec([np.radians(deg), 0, 0]).as_matrix(), np.zeros(3))
            start[k] = start[k - 1] @ turn @ invert(poses[k - 1]) @ poses[k]
        aa, ab, aq, apx = _along_anchors(camera, poses, start, rng)
        rows = epipolar_rows(camera, start, aa, ab, aq, np.ones(len(aa), bool))
        assert np.allclose(np.linalg.norm(rows[:, 0], axis=1), 1.0) and np.all(rows[:, 1] == 0)
        for name, r in (("both", None), ("along", rows)):
            problem = BundleProblem(poses, pts, f, p, px, aa, ab, aq, apx, anchor_rows=r)
            res = bundle_adjust(camera, problem, BundleConfig(max_evaluations=100))
            errors[name, deg] = max(
                np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3].T @ G[:3, :3]).as_rotvec()))
                for T, G in zip(res.world_from_rig, poses, strict=True)
            )
    assert errors["both", 1.0] > 0.12 and errors["both", 1.0] > 2 * errors["both", 0.3], errors
    assert errors["along", 1.0] < 0.05 and errors["along", 0.3] < 0.05, errors
    assert abs(errors["along", 1.0] - errors["along", 0.3]) < 0.005, errors
    # A 2-D anchor (a wall-placed feature) keeps both components.
    assert np.all(epipolar_rows(camera, poses, aa, ab, aq, np.zeros(len(aa), bool)) == np.eye(2))


def test_cross_rows_is_numpys_cross_to_the_bit() -> None:
    rng = np.random.default_rng(5)
    q = rng.normal(size=(1000, 3)) * rng.uniform(1e-6, 1e3, (1000, 1))
    r = rng.normal(size=(1000, 3))
    got = cross_rows(q, *(np.ascontiguousarray(r[:, i]) for i in range(3)))
    assert np.array_equal(got, np.cross(q, r))

"""Calibration accuracy on simulated calibration sets with random true parameters.

For each seed: ``simulate --scenario calibration`` (camera off the mirror's focus,
mirror tilted up to 1 deg, laser tilted up to 2 deg), ``calibrate camera`` (unified
model) and ``calibrate laser``; prints per set the reprojection RMS (px) and the laser
plane's errors against the truth: normal angle (deg) and offset (mm), both in the true
rig (mirror) frame ("raw") and after aligning the calibrated frame to it with the
boards' corners ("aligned": the calibrated model's frame is the best central
approximation of a non-central rig, not the mirror frame exactly).

It also measures what a user needs directly: the laser ring of a straight 202 mm pipe
(the paper's), traced through the true rig (coaxial, and 5 mm off-centre), seen
through the calibrated camera on the calibrated laser plane: "ring D" is the worst
error of the fitted ring's diameter (ellipse minor axis) against 202 mm.

    python benchmarks/bench_calibration.py --sets 10 [--size 800x600] [--views 16]
        [--design] [--save-rigs DIR]

``--design``: the paper rig exactly as designed (camera at the focus, laser z = -82 mm)
instead of random true parameters; ``--save-rigs``: write each calibrated rig.yaml
there (e.g. to reconstruct ``simulate --scenario paper`` with it).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from omnipipe.calibrate.camera import (
    calibrate_unified,
    calibrated_rig,
    detect_corners,
    load_images,
    mirror_annulus,
    parse_target,
)
from omnipipe.calibrate.laser import calibrate_laser, laser_plane, ring_section_axes
from omnipipe.camera import camera_from_rig
from omnipipe.rig import Rig
from omnipipe.rig_yaml import save_rig
from omnipipe.sim.calibration import TARGET, ring_pixels, write_calibration_set

PIPE_MM = 202.0


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with dst ~ R src + t."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def one_set(seed: int, size: tuple[int, int], views: int, root: Path, design: bool = False,
            save: Path | None = None) -> dict[str, float]:
    out = root / f"set{seed}"
    t0 = time.perf_counter()
    truth = write_calibration_set(out, seed=seed, size=size, views=views, design=design)
    t_render = time.perf_counter() - t0
    target = parse_target(f"checkerboard:{TARGET[0]}x{TARGET[1]}:{TARGET[2]:g}")
    images = load_images(sorted((out / "images").glob("*.png")))
    t0 = time.perf_counter()
    corners = {i: c for i, im in enumerate(images) if (c := detect_corners(im, target)) is not None}
    cal = calibrate_unified(corners, target, size)
    rig = calibrated_rig(cal, size, mirror_annulus(images, cal.cx, cal.cy))
    las = calibrate_laser(images, rig, target)
    t_cal = time.perf_counter() - t0
    k_true = truth.laser_k / np.linalg.norm(truth.laser_k[:3])
    k = las.k

    def errors(kt: np.ndarray) -> tuple[float, float]:
        ang = float(np.degrees(np.arccos(min(1.0, abs(float(k[:3] @ kt[:3]))))))
        return ang, float(abs(k[3]) - abs(kt[3]))

    raw = errors(k_true)
    # align the calibrated frame to the truth with the boards' corners (nearest neighbours)
    obj = target.object_points()
    j, i = np.mgrid[0 : TARGET[1], 0 : TARGET[0]]
    obj_true = np.stack([(i.ravel() + 1), (j.ravel() + 1), 0 * i.ravel()], 1) * TARGET[2]
    src, dst = [], []
    for v, pose in las.rig_from_board.items():
        est = obj @ pose[:3, :3].T + pose[:3, 3]
        tru = obj_true @ truth.boards[v][:3, :3].T + truth.boards[v][:3, 3]
        nn = np.argmin(np.linalg.norm(est[:, None] - tru[None], axis=2), axis=1)
        src.append(tru[nn])
        dst.append(est)
    r, t = _kabsch(np.concatenate(src), np.concatenate(dst))  # cal_from_true
    n = r @ k_true[:3]
    aligned = errors(np.array([*n, k_true[3] - n @ t]))
    frame_deg = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    camera = camera_from_rig(rig)
    ring = max((ring_section_axes(camera, k, ring_pixels(truth, PIPE_MM, c))[0] - PIPE_MM
                for c in ((0.0, 0.0), (5.0, 0.0))), key=abs)
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
        save_rig(Rig(rig.camera, rig.mirror, laser_plane(las, "red"), rig.model),
                 save / f"rig_seed{seed}.yaml")
    return {
        "seed": seed, "views": len(cal.used), "rms_px": cal.rms_px,
        "normal_raw_deg": raw[0], "offset_raw_mm": raw[1],
        "normal_aligned_deg": aligned[0], "offset_aligned_mm": aligned[1],
        "ring_mm": ring, "frame_rot_deg": frame_deg, "frame_shift_mm": float(np.linalg.norm(t)),
        "sigma_normal_deg": las.normal_sigma_deg, "sigma_offset_mm": las.offset_sigma_mm,
        "laser_views": len(las.per_view), "t_render_s": t_render, "t_calibrate_s": t_cal,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--design", action="store_true", help="the paper rig as designed")
    ap.add_argument("--save-rigs", type=Path, default=None, help="write calibrated rigs here")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    rows = []
    print("| seed | views | RMS px | normal raw deg | offset raw mm | normal aligned deg | "
          "offset aligned mm | ring D mm | frame rot deg / shift mm | "
          "1-sigma normal deg / offset mm |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.sets):
            r = one_set(seed, size, args.views, Path(tmp), args.design,  # type: ignore[arg-type]
                        args.save_rigs)
            rows.append(r)
            print(f"| {seed} | {r['views']} | {r['rms_px']:.3f} | {r['normal_raw_deg']:.3f} | "
                  f"{r['offset_raw_mm']:+.3f} | {r['normal_aligned_deg']:.3f} | "
                  f"{r['offset_aligned_mm']:+.3f} | {r['ring_mm']:+.3f} | {r['frame_rot_deg']:.3f} / {r['frame_shift_mm']:.3f} | "
                  f"{r['sigma_normal_deg']:.3f} / {r['sigma_offset_mm']:.3f} |", flush=True)
    for key in ("rms_px", "normal_raw_deg", "offset_raw_mm", "normal_aligned_deg", "offset_aligned_mm",
                "ring_mm"):
        vals = np.array([r[key] for r in rows])
        print(f"{key}: max |.| {np.abs(vals).max():.3f}, mean {vals.mean():+.3f}")
    print(f"render {np.mean([r['t_render_s'] for r in rows]):.1f} s/set, calibrate "
          f"{np.mean([r['t_calibrate_s'] for r in rows]):.1f} s/set")


if __name__ == "__main__":
    main()

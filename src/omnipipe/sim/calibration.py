"""Calibration sets: checkerboard views through the mirror, with the laser on the board.

``omnipipe simulate --scenario calibration --seed S --out D`` writes

```
D/
  images/view_NN.png      RGB: the lit checkerboard; the red laser line where the
                          laser plane cuts the board (absent from green and blue)
  nominal_rig.yaml        the rig as designed (paper rig), no laser: a starting point
  target.txt              the checkerboard: "checkerboard:COLSxROWS:SQUARE_MM"
  ground_truth/
    calibration.json      the true camera, mirror, laser and board poses
```

Physical truth (not a single-viewpoint model): a pinhole camera with image distance
``f_px`` and principal point (``cx``, ``cy``) looks into the hyperboloid mirror
(X^2+Y^2)/a^2 - (Z+c)^2/b^2 = -1 (rig frame = mirror frame: origin at the mirror's
focus, z along its axis). Its pinhole sits ``camera_offset_mm`` off the mirror's second
focus (0, 0, -2c) and its optical axis is tilted by ``mirror_tilt_deg`` from the mirror
axis (the mirror tilted in its mount), so the image is only approximately central.
Each pixel's ray (2x2 supersampled) is reflected exactly at the mirror and meets the
board plane. The laser plane ``laser_plane`` (k1..k4 in the rig frame, Eq. 4) is tilted
up to 2 deg; its line on the board is a Gaussian sheet of 0.35 mm sigma.

``design=True`` (:func:`write_calibration_set`; ``design`` in calibration.json) renders
the paper rig exactly as designed instead, the rig of ``simulate --scenario paper``.
:func:`ring_pixels` gives the true laser ring of a pipe of known diameter, to check a
calibrated rig without the image chain (benchmarks/bench_calibration.py).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from omnipipe.errors import ConfigError
from omnipipe.output import atomic_output_dir
from omnipipe.rig import Rig
from omnipipe.rig_yaml import save_rig

CALIBRATION_SCENARIO = "calibration"
DEFAULT_SIZE = (800, 600)
DEFAULT_VIEWS = 16
TARGET = (8, 6, 12.0)  # inner corners (cols, rows), square (mm)
HYPER70_RIM_RADIUS_MM = 35.0
LASER_SIGMA_MM = 0.35


@dataclass(frozen=True)
class CalibrationTruth:
    """The true, randomised rig of one calibration set (rig frame = mirror frame, mm, px)."""

    nominal: Rig
    a: float
    b: float
    f_px: float
    cx: float
    cy: float
    camera_offset_mm: np.ndarray  # (3,) pinhole minus (0, 0, -2c)
    rig_from_camera: np.ndarray  # (3, 3) rotation: camera axes (x cols, y rows, z optical) in rig
    laser_k: np.ndarray  # (4,) k1..k4, unit normal, mm
    boards: list[np.ndarray]  # (4, 4) rig_from_board per view (board x along cols, y rows)

    @property
    def pinhole(self) -> np.ndarray:
        """(3,) the camera's pinhole in the rig frame (mm)."""
        c = math.hypot(self.a, self.b)
        return np.array([0.0, 0.0, -2.0 * c]) + self.camera_offset_mm


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues((np.asarray(axis, float) / np.linalg.norm(axis) * angle).reshape(3, 1))[0]


def draw_truth(
    seed: int, size: tuple[int, int] = DEFAULT_SIZE, views: int = DEFAULT_VIEWS, design: bool = False
) -> CalibrationTruth:
    """Random true parameters around the paper rig, and board poses.

    Camera pinhole up to 0.3 mm off the focus per axis, mirror tilted 0-1 deg, principal
    point +-1 % of the image height off centre (+-6 px at 600 rows), f +-1 %, laser
    normal tilted 0-2 deg, its distance 82 +- 3 mm. Half the boards straddle the laser
    plane (laser calibration), the rest spread over the mirror's view.

    ``design``: the paper rig exactly as designed (``paper_rig(width, height)``: camera
    at the focus, no tilt, laser plane z = -82 mm), the rig of ``simulate --scenario
    paper``; only the board poses are random (the same draws as without it).
    """
    from omnipipe.sim.scenario import paper_rig

    if seed < 0:
        raise ConfigError("--seed", f"must be >= 0, got {seed}")
    rng = np.random.default_rng(seed)
    width, height = size
    nominal = paper_rig(width, height)
    nominal = Rig(nominal.camera, nominal.mirror, None)
    cam = nominal.camera
    a, b = nominal.mirror.a, nominal.mirror.b  # type: ignore[union-attr]
    offset = rng.uniform(-0.3, 0.3, 3)
    tilt = math.radians(rng.uniform(0.0, 1.0))
    tilt_axis = np.array([math.cos(p := rng.uniform(0, 2 * math.pi)), math.sin(p), 0.0])
    rig_from_camera = _rotation(tilt_axis, tilt)
    pp = rng.uniform(-0.01, 0.01, 2) * height
    f_px = cam.f * (1.0 + rng.uniform(-0.01, 0.01))
    laser_tilt = math.radians(rng.uniform(0.0, 2.0))
    q = rng.uniform(0, 2 * math.pi)
    n = np.array([math.sin(laser_tilt) * math.cos(q), math.sin(laser_tilt) * math.sin(q), math.cos(laser_tilt)])
    laser_k = np.array([*n, 82.0 + rng.uniform(-3.0, 3.0)])
    if design:
        offset, rig_from_camera, pp, f_px = np.zeros(3), np.eye(3), np.zeros(2), cam.f
        laser = paper_rig(width, height).laser
        n, laser_k = np.array([0.0, 0.0, 1.0]), np.array(laser.k, float)  # type: ignore[union-attr]
    boards = []
    cols, rows, square = TARGET
    for i in range(views):
        az = 2 * math.pi * (i + rng.uniform(-0.3, 0.3)) / views
        if i % 2 == 0:  # straddles the laser plane
            dist = rng.uniform(95.0, 130.0)
            z = -laser_k[3] / n[2] + rng.uniform(-12.0, 12.0)
        else:
            dist = rng.uniform(80.0, 120.0)
            elev = math.radians(rng.uniform(-35.0, 12.0))
            z = dist * math.tan(elev)
        centre = np.array([dist * math.cos(az), dist * math.sin(az), z])
        # board normal towards the axis; board y along -z (image rows run down the wall)
        normal = -np.array([math.cos(az), math.sin(az), 0.0])
        y_axis = np.array([0.0, 0.0, -1.0])
        x_axis = np.cross(y_axis, normal)
        r = np.stack([x_axis, y_axis, normal], axis=1)
        r = r @ _rotation(np.array([1.0, 0, 0]), math.radians(rng.uniform(-30, 30)))
        r = r @ _rotation(np.array([0, 1.0, 0]), math.radians(rng.uniform(-30, 30)))
        r = r @ _rotation(np.array([0, 0, 1.0]), math.radians(rng.uniform(-20, 20)))
        t = centre - r @ np.array([(cols + 1) * square / 2, (rows + 1) * square / 2, 0.0])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r, t
        boards.append(pose)
    return CalibrationTruth(
        nominal, a, b, f_px, cam.cx + pp[0], cam.cy + pp[1], offset, rig_from_camera, laser_k, boards
    )


def trace_rays(truth: CalibrationTruth, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The physical rays of (N, 2) pixels after the mirror: (origins, unit dirs, hit mask)."""
    a, b = truth.a, truth.b
    c = math.hypot(a, b)
    d_cam = np.stack(
        [(pixels[:, 0] - truth.cx) / truth.f_px, (pixels[:, 1] - truth.cy) / truth.f_px, np.ones(len(pixels))],
        axis=1,
    )
    d = d_cam @ truth.rig_from_camera.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = truth.pinhole
    # (x^2 + y^2)/a^2 - (z + c)^2/b^2 + 1 = 0 along o + t d
    oz = o[2] + c
    qa = (d[:, 0] ** 2 + d[:, 1] ** 2) / a**2 - d[:, 2] ** 2 / b**2
    qb = 2 * ((o[0] * d[:, 0] + o[1] * d[:, 1]) / a**2 - oz * d[:, 2] / b**2)
    qc = (o[0] ** 2 + o[1] ** 2) / a**2 - oz**2 / b**2 + 1.0
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        roots = np.stack([(-qb - sq) / (2 * qa), (-qb + sq) / (2 * qa)], axis=1)
        p_z = o[2] + roots * d[:, 2:3] + c
        roots = np.where((roots > 0) & (p_z > 0), roots, np.inf)
    t = roots.min(axis=1)
    hit = np.isfinite(t)
    t = np.where(hit, t, 0.0)
    p = o + t[:, None] * d
    hit &= np.hypot(p[:, 0], p[:, 1]) <= HYPER70_RIM_RADIUS_MM
    grad = np.stack([2 * p[:, 0] / a**2, 2 * p[:, 1] / a**2, -2 * (p[:, 2] + c) / b**2], axis=1)
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    r = d - 2.0 * np.sum(d * grad, axis=1, keepdims=True) * grad
    return p, r, hit


def ring_pixels(
    truth: CalibrationTruth, diameter_mm: float, centre_mm: tuple[float, float] = (0.0, 0.0),
    angles: int = 720,
) -> np.ndarray:
    """(N, 2) pixels (col, row) of the true laser ring in a straight pipe, noise-free.

    The pipe (inner diameter ``diameter_mm``) has its axis along the rig's z axis through
    (x, y) = ``centre_mm``; along each of ``angles`` image rays from the principal point
    the physical rays are traced (:func:`trace_rays`) to the wall and the pixel where the
    wall point crosses the laser plane is interpolated (0.25 px steps). For measuring a
    calibrated rig against the truth without the image chain.
    """
    cam = truth.nominal.camera
    radius = diameter_mm / 2.0
    radii = np.arange(cam.radius_min or 5.0, cam.radius_max or min(cam.cx, cam.cy), 0.25)
    out = []
    k = truth.laser_k
    for phi in np.linspace(0.0, 2.0 * math.pi, angles, endpoint=False):
        px = np.stack([truth.cx + radii * math.cos(phi), truth.cy + radii * math.sin(phi)], axis=1)
        o, d, hit = trace_rays(truth, px)
        oc = o[:, :2] - np.asarray(centre_mm, float)
        qa = d[:, 0] ** 2 + d[:, 1] ** 2
        qb = 2.0 * np.sum(oc * d[:, :2], axis=1)
        qc = np.sum(oc * oc, axis=1) - radius**2
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-qb + np.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)
        s = (o + t[:, None] * d) @ k[:3] + k[3]
        s[~hit] = np.nan
        i = np.flatnonzero(np.isfinite(s[:-1]) & np.isfinite(s[1:]) & (np.sign(s[:-1]) != np.sign(s[1:])))
        f = s[i] / (s[i] - s[i + 1])
        out.append(px[i] + f[:, None] * (px[i + 1] - px[i]))
    return np.concatenate(out) if out else np.zeros((0, 2))


Traced = list[tuple[np.ndarray, np.ndarray, np.ndarray]]


def trace_image(truth: CalibrationTruth, supersample: int = 2) -> Traced:
    """The physical rays of every image sample: per sub-pixel offset (row-major over
    ``supersample`` x ``supersample``), :func:`trace_rays` of every pixel (H*W rows).
    The same for every view of a set: traced once, rendered many times."""
    cam = truth.nominal.camera
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
    out = []
    for dy in offs:
        for dx in offs:
            px = np.stack([cols.ravel() + dx, rows.ravel() + dy], axis=1).astype(float)
            out.append(trace_rays(truth, px))
    return out


def render_view(
    truth: CalibrationTruth, view: int, rng: np.random.Generator, supersample: int = 2,
    traced: Traced | None = None,
) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of board ``view`` with the laser line.

    ``traced``: :func:`trace_image` of ``truth`` with this ``supersample`` (computed here
    when None; pass it to render several views of one set).
    """
    cam = truth.nominal.camera
    w, h = cam.width, cam.height
    ss = supersample
    if traced is None:
        traced = trace_image(truth, ss)
    rows, cols = np.mgrid[0:h, 0:w]
    gray = np.zeros(h * w)
    laser = np.zeros(h * w)
    pose = truth.boards[view]
    board_from_rig = np.linalg.inv(pose)
    n_cols, n_rows, square = TARGET
    k = truth.laser_k
    r_centre = np.hypot(cols.ravel() - cam.cx, rows.ravel() - cam.cy)
    blind = r_centre < (cam.radius_min or 0.0)
    for o, d, hit in traced:
        ob = o @ board_from_rig[:3, :3].T + board_from_rig[:3, 3]
        db = d @ board_from_rig[:3, :3].T
        with np.errstate(invalid="ignore", divide="ignore"):
            t = -ob[:, 2] / db[:, 2]
        on = hit & (t > 0)
        q = ob + np.where(on, t, 0.0)[:, None] * db
        u, v = q[:, 0] / square, q[:, 1] / square
        inside = on & (u >= 0) & (u <= n_cols + 1) & (v >= 0) & (v <= n_rows + 1)
        margin = on & (u >= -0.6) & (u <= n_cols + 1.6) & (v >= -0.6) & (v <= n_rows + 1.6)
        checker = (np.floor(u) + np.floor(v)) % 2 == 0
        val = np.where(hit, 0.25, 0.02)
        val = np.where(margin, 0.85, val)
        val = np.where(inside & checker, 0.08, val)
        gray += np.where(blind, 0.03, val) / ss**2
        p_rig = o + np.where(on, t, 0.0)[:, None] * d
        dist = p_rig @ k[:3] + k[3]
        laser += np.where(margin & ~blind, np.exp(-0.5 * (dist / LASER_SIGMA_MM) ** 2), 0.0) / ss**2
    gray = cv2.GaussianBlur(gray.reshape(h, w), (0, 0), 0.5)
    laser = cv2.GaussianBlur(laser.reshape(h, w), (0, 0), 0.5)
    img = np.stack([0.7 * gray + 0.8 * laser, gray, gray], axis=2)
    img = img + rng.normal(0.0, 1.5 / 255, img.shape)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def write_calibration_set(
    out: str | Path,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    views: int | None = None,
    force: bool = False,
    design: bool = False,
) -> CalibrationTruth:
    """Render a calibration set (module docstring) into ``out``, atomically.

    ``design``: the paper rig as designed instead of random true parameters
    (:func:`draw_truth`).

    Raises:
        ConfigError: bad seed, size or view count. OutputError: ``out`` may not be written.
    """
    size = size or DEFAULT_SIZE
    views = DEFAULT_VIEWS if views is None else views
    if views < 3:
        raise ConfigError("--frames", f"a calibration set needs at least 3 views, got {views}")
    if size[0] < 200 or size[1] < 150:
        raise ConfigError("--size", f"calibration views need at least 200x150 px, got {size[0]}x{size[1]}")
    truth = draw_truth(seed, size, views, design=design)
    rng = np.random.default_rng(seed + 1_000_003)
    with atomic_output_dir(Path(out), force=force) as tmp:
        (tmp / "images").mkdir()
        (tmp / "ground_truth").mkdir()
        traced = trace_image(truth)
        for i in range(views):
            img = render_view(truth, i, rng, traced=traced)
            cv2.imwrite(str(tmp / "images" / f"view_{i:02d}.png"), img[:, :, ::-1])
        save_rig(truth.nominal, tmp / "nominal_rig.yaml")
        cols, rows, square = TARGET
        (tmp / "target.txt").write_text(f"checkerboard:{cols}x{rows}:{square:g}\n", encoding="utf-8")
        gt = {
            "design": design,
            "mirror": {"a": truth.a, "b": truth.b},
            "camera": {
                "f_px": truth.f_px,
                "cx": truth.cx,
                "cy": truth.cy,
                "offset_from_focus_mm": truth.camera_offset_mm.tolist(),
                "rig_from_camera": truth.rig_from_camera.tolist(),
                "mirror_tilt_deg": math.degrees(
                    math.acos(min(1.0, float(truth.rig_from_camera[2, 2])))
                ),
            },
            "laser": {
                "plane": truth.laser_k.tolist(),
                "tilt_deg": math.degrees(math.acos(min(1.0, abs(float(truth.laser_k[2]))))),
            },
            "target": {"cols": cols, "rows": rows, "square_mm": square},
            "rig_from_board": [p.tolist() for p in truth.boards],
            "frame": "rig = mirror frame: origin at the mirror focus, z along the mirror axis "
            "from the camera towards the mirror, x along image columns, y along rows; mm",
        }
        (tmp / "ground_truth" / "calibration.json").write_text(json.dumps(gt, indent=1), encoding="utf-8")
    return truth


def simulate_main(args: Any) -> int:
    """``omnipipe simulate --scenario calibration``: --seed, --out, --size, --frames (views), --force."""
    import time

    from omnipipe.output import prepare_output_dir

    out = args.out
    prepare_output_dir(out, force=bool(getattr(args, "force", False)))
    start = time.perf_counter()
    truth = write_calibration_set(
        out,
        seed=int(getattr(args, "seed", 0)),
        size=getattr(args, "size", None),
        views=getattr(args, "frames", None),
        force=bool(getattr(args, "force", False)),
        design=bool(getattr(args, "design", False)),
    )
    cam = truth.nominal.camera
    print(
        f"wrote {out}: {len(truth.boards)} calibration views {cam.width}x{cam.height} in "
        f"{time.perf_counter() - start:.1f} s (images/, target.txt, nominal_rig.yaml; "
        "truth in ground_truth/calibration.json)"
    )
    return 0

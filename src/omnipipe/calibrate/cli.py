"""``omnipipe calibrate camera|laser`` and ``omnipipe rig import-ocam``.

Every refusal (no target found, too few views, wrong target size, images of mixed
sizes, an existing --out without --force) is one line and exit 1, with nothing written.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from omnipipe import cli_values
from omnipipe.errors import ConfigError, OutputError
from omnipipe.rig import LASER_CHANNELS, Mirror, Rig
from omnipipe.rig_yaml import load_rig, rig_from_dict, save_rig

# A calibration worse than this (px RMS) is refused: wrong target size or bad detections.
MAX_RMS_PX = 1.0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``calibrate`` and ``rig`` sub-commands."""
    cal = sub.add_parser(
        "calibrate",
        help="calibrate a real rig's camera or laser plane from checkerboard images",
        description="Calibrate the camera (checkerboard views through the mirror) or the laser "
        "plane (the laser line on the board at several poses); docs/calibration.md.",
    )
    csub = cal.add_subparsers(dest="what", required=True, metavar="{camera,laser}")
    cam = csub.add_parser("camera", help="camera model from checkerboard views")
    cam.add_argument("images", nargs="+", help="images of the checkerboard through the mirror")
    cam.add_argument("--target", required=True, type=_target,
                     help="checkerboard:COLSxROWS:SQUARE_MM (inner corners)")
    cam.add_argument("--model", choices=("unified", "hyperboloid"), default="unified")
    cam.add_argument("--init", help="rig.yaml to start from (e.g. the design), optional")
    cam.add_argument("--mirror-a", type=cli_values.number("--mirror-a", 0.0, 1e4, open_lo=True, unit="mm"),
                     default=None,
                     help="hyperboloid: the mirror's a (mm) from its datasheet (else --init's)")
    cam.add_argument("--out", required=True, help="rig.yaml to write (camera only, no laser)")
    cam.add_argument("--force", action="store_true", help="replace an existing --out file")
    cam.set_defaults(func=_camera)
    las = csub.add_parser("laser", help="laser plane from the laser line on the board")
    las.add_argument("images", nargs="+", help="images of the board cut by the laser line")
    las.add_argument("--rig", required=True, help="rig.yaml with the calibrated camera")
    las.add_argument("--target", required=True, type=_target,
                     help="checkerboard:COLSxROWS:SQUARE_MM (inner corners)")
    las.add_argument("--channel", default="red", choices=LASER_CHANNELS)
    las.add_argument("--out", required=True, help="rig.yaml to write (the rig plus its laser)")
    las.add_argument("--force", action="store_true", help="replace an existing --out file")
    las.set_defaults(func=_laser)

    rig = sub.add_parser(
        "rig",
        help="convert calibrations from other tools into rig.yaml (import-ocam)",
        description="Rig file tools.",
    )
    rsub = rig.add_subparsers(dest="what", required=True, metavar="{import-ocam}")
    imp = rsub.add_parser("import-ocam", help="OCamCalib calib_results.txt -> rig.yaml (model ocam)")
    imp.add_argument("calib_results", help="OCamCalib's calib_results.txt")
    imp.add_argument("--out", required=True, help="rig.yaml to write")
    imp.add_argument("--laser-from", help="take the laser section of this rig.yaml")
    imp.add_argument("--radius-min", type=cli_values.number("--radius-min", 0.0, 1e5, unit="px"), default=None, help="blind centre radius (px)")
    imp.add_argument("--radius-max", type=cli_values.number("--radius-max", 0.0, 1e5, unit="px"), default=None, help="mirror rim radius (px)")
    imp.add_argument("--force", action="store_true", help="replace an existing --out file")
    imp.set_defaults(func=_import_ocam)


def _target(text: str) -> str:
    """``--target`` checked while the command line is parsed (one line, exit 1)."""
    from omnipipe.calibrate.camera import parse_target

    parse_target(text)
    return text


def _check_out(out: str, force: bool, inputs: list[str]) -> Path:
    path = Path(out)
    if path.is_dir():
        raise OutputError(f"{out}: is a directory; --out names the rig.yaml to write")
    if not path.parent.is_dir():
        raise OutputError(f"{out}: folder {path.parent} does not exist")
    for p in inputs:
        if p and Path(p).exists() and path.exists() and os.path.samefile(p, path):
            raise OutputError(f"{out}: is one of the inputs")
    if path.exists() and not force:
        raise OutputError(f"{out}: already exists (use --force to replace it)")
    return path


def _write_rig(rig: Rig, path: Path) -> None:
    rig_from_dict(rig.to_dict(), str(path))  # what is written must load
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        save_rig(rig, tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _camera(args: argparse.Namespace) -> int:
    from omnipipe.calibrate.camera import (
        CalibrationError,
        calibrate_unified,
        calibrated_rig,
        detect_corners,
        load_images,
        mirror_annulus,
        parse_target,
    )

    target = parse_target(args.target)
    out = _check_out(args.out, args.force, [*args.images, args.init or ""])
    init = load_rig(args.init) if args.init else None
    images = load_images(args.images)
    h, w = images[0].shape[:2]
    if init is not None and (init.camera.width, init.camera.height) != (w, h):
        raise ConfigError("--init", f"is {init.camera.width}x{init.camera.height}, the images {w}x{h}")
    corners = {}
    for i, img in enumerate(images):
        c = detect_corners(img, target)
        if c is not None:
            corners[i] = c
    if not corners:
        raise CalibrationError(
            f"no {target} found in any of the {len(images)} images "
            "(check --target: COLSxROWS counts inner corners)"
        )
    seed, centre = None, None
    if init is not None:
        from omnipipe.camera import camera_from_rig
        from omnipipe.camera.convert import fit_unified

        seed, cx, cy, _ = fit_unified(camera_from_rig(init))
        centre = (cx, cy)
    hyper = args.model == "hyperboloid"
    cal = calibrate_unified(corners, target, (w, h), init=seed, init_centre=centre,
                            distortion=not hyper)
    if cal.rms_px > MAX_RMS_PX:
        raise CalibrationError(
            f"reprojection RMS {cal.rms_px:.2f} px (> {MAX_RMS_PX:g}): the corners do not fit one "
            f"camera; is the board really {target.cols}x{target.rows} inner corners (a smaller "
            "--target matches part of a bigger board)? nothing written"
        )
    radii = mirror_annulus(images, cal.cx, cal.cy)
    pitch = init.camera.pixel_pitch if init is not None else None
    rig = calibrated_rig(cal, (w, h), radii, pixel_pitch=pitch)
    if hyper:
        a = args.mirror_a if args.mirror_a is not None else (init.mirror.a if init and init.mirror else None)
        if a is None or not a > 0:
            raise ConfigError("--mirror-a", "the hyperboloid model needs the mirror's a (mm): "
                              "give --mirror-a or an --init rig with a mirror")
        rig = _as_hyperboloid(rig, float(a))
    for i in cal.used:
        print(f"{args.images[i]}: {cal.per_image_rms_px[i]:.3f} px")
    missing = len(images) - len(cal.used)
    print(
        f"reprojection RMS {cal.rms_px:.3f} px over {len(cal.used)} views"
        + (f" (target not found in {missing})" if missing else "")
        + f"; xi {cal.params.xi:.4f}, fx {cal.params.fx:.2f}, fy {cal.params.fy:.2f}, "
        f"centre ({cal.cx:.2f}, {cal.cy:.2f}) px"
    )
    _write_rig(rig, out)
    print(f"wrote {out} (camera model {rig.camera_model}; no laser section yet)")
    return 0


def _as_hyperboloid(rig: Rig, a: float) -> Rig:
    """The unified (no distortion) rig as the hyperboloid of Eq. 1-3 with mirror ``a``."""
    from scipy.optimize import least_squares

    from omnipipe.camera import camera_from_parts, camera_from_rig
    from omnipipe.camera.convert import _samples

    src = camera_from_rig(rig)
    px = _samples(src)
    rays = src.unproject(px)

    def residual(x: np.ndarray) -> np.ndarray:
        cam = camera_from_parts(replace(rig.camera, f=float(x[1]), radius_max=None), Mirror(a, float(x[0])), None)
        return np.nan_to_num((cam.project(rays)[0] - px).ravel(), nan=1e3)

    sol = least_squares(residual, np.array([1.5 * a, 5.0 * rig.camera.f]), x_scale="jac")
    b, f = float(sol.x[0]), float(sol.x[1])
    return Rig(replace(rig.camera, f=f), Mirror(a, b), rig.laser, None)


def _laser(args: argparse.Namespace) -> int:
    from omnipipe.calibrate.camera import load_images, parse_target
    from omnipipe.calibrate.laser import calibrate_laser, laser_plane

    target = parse_target(args.target)
    out = _check_out(args.out, args.force, [*args.images, args.rig])
    rig = load_rig(args.rig)
    images = load_images(args.images)
    h, w = images[0].shape[:2]
    if (rig.camera.width, rig.camera.height) != (w, h):
        raise ConfigError(args.images[0], f"is {w}x{h} but {args.rig} says {rig.camera.width}x{rig.camera.height}")
    cal = calibrate_laser(images, rig, target, args.channel)
    for i, (n, rms) in sorted(cal.per_view.items()):
        print(f"{args.images[i]}: {n} laser points, {rms:.3f} mm RMS from the plane")
    k = cal.k
    print(
        f"laser plane k = [{k[0]:.6f}, {k[1]:.6f}, {k[2]:.6f}, {k[3]:.4f}] from {len(cal.points)} "
        f"points in {len(cal.per_view)} views: residual {cal.rms_mm:.3f} mm RMS; "
        f"1-sigma normal {cal.normal_sigma_deg:.4f} deg, offset {cal.offset_sigma_mm:.4f} mm"
    )
    new = Rig(rig.camera, rig.mirror, laser_plane(cal, args.channel), rig.model)
    _write_rig(new, out)
    print(f"wrote {out}")
    return 0


def _import_ocam(args: argparse.Namespace) -> int:
    from omnipipe.calibrate.ocam_io import rig_from_ocam

    out = _check_out(args.out, args.force, [args.calib_results, args.laser_from or ""])
    other = load_rig(args.laser_from) if args.laser_from else None
    for name, v in (("--radius-min", args.radius_min), ("--radius-max", args.radius_max)):
        if v is not None and not (np.isfinite(v) and v >= 0):
            raise ConfigError(name, f"must be a finite radius >= 0 px, got {v}")
    rig = rig_from_ocam(args.calib_results, other, args.radius_min, args.radius_max)
    _write_rig(rig, out)
    cam = rig.camera
    print(f"wrote {out} (camera model ocam, frames {cam.width}x{cam.height}, radii "
          f"{cam.radius_min}..{cam.radius_max} px"
          + (", laser from " + args.laser_from if other else ", no laser section") + ")")
    if other and (other.camera.width, other.camera.height) != (cam.width, cam.height):
        print(f"note: {args.laser_from} is {other.camera.width}x{other.camera.height}; its laser "
              "plane is in mm in the rig frame and is taken as is (same camera, mirror and laser)")
    return 0
